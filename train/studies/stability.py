"""Training stability: a long run of UniqueSplat (c) on the demo's synthetic training set,
recording loss, the gradient norms of the network's parts (before clipping) and skipped
non-finite steps; writes a chart and a JSON summary.

    python train/studies/stability.py        # 2100 steps (3x the demo), ~15 min on 2 cores
    python train/studies/stability.py --steps 6000 --preset small --out outputs/stability_small

Needs the demo's data (``usplat demo`` or ``usplat bench`` makes it in outputs/demo/data).
A killed run resumes where it stopped when started again with the same arguments.
"""

import argparse
import json
import logging
from pathlib import Path

from usplat_dr.io import write_json
from usplat_dr.training import train
from usplat_dr.training.recipes import RECIPES, training_config
from usplat_dr.training.run_log import curves, stability


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default="outputs/demo/data")
    p.add_argument("--out", default="outputs/stability")
    p.add_argument("--steps", type=int, default=2100)
    p.add_argument("--preset", default="tiny")
    p.add_argument("--variant", default="full")
    args = p.parse_args()
    logging.basicConfig(level=logging.WARNING)
    data = Path(args.data)
    if not (data / "demo.json").is_file():
        raise SystemExit(f"--data {data}: no demo data set there; run `usplat demo` (or "
                         f"`usplat bench`) first, or pass --data")
    recipe = RECIPES["full"]
    run = Path(args.out) / f"train_{args.preset}_{args.variant}"
    cfg = training_config(data, run, recipe, args.variant, args.preset)
    cfg["train"].update(steps=args.steps, checkpoint_every=max(args.steps // 10, 1),
                        validate_every=args.steps)
    train(cfg, resume=True)
    summary = stability(run)
    write_json(Path(args.out) / "stability.json", summary)
    curves({args.variant: run}, Path(args.out) / "stability.png")
    print(json.dumps(summary, indent=1))
    print(f"wrote {args.out}/stability.json and stability.png")


if __name__ == "__main__":
    main()
