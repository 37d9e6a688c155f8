"""Per-scene Gaussian optimisation on a synthetic scene (the renderer check).

Same as ``usplat fit``; run ``python train/examples/fit_gaussians.py --help`` for the options, e.g.

    python train/examples/fit_gaussians.py --kind indoor --seed 0 --resolution 64 64 \
        --iterations 1500
"""

import sys

from usplat_dr.cli import main

if __name__ == "__main__":
    sys.exit(main(["fit", *sys.argv[1:]]))
