"""Training entry point (the same as ``usplat train``).

    python train/train.py --config synthetic_tiny.yaml train.steps=500
    torchrun --nproc_per_node 2 train/train.py --config ... data_loader.batch_size=1
    python train/train.py --config ... --resume      # continue a killed run exactly
"""

import sys

from usplat_dr.cli import main

if __name__ == "__main__":
    sys.exit(main(["train", *sys.argv[1:]]))
