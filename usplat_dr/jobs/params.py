"""``usplat params``: the parameter count of a UniqueSplat configuration, per part."""

import argparse
import logging

from usplat_dr.model.uniquesplat import PAPER_PARAMETERS, PRESETS, UniqueSplat


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", default="paper", choices=sorted(PRESETS),
                   help="the model size preset")
    p.add_argument("--variant", default="all", choices=["all", "baseline", "agnostic", "full"],
                   help="(a) baseline, (b) agnostic, (c) full, or all three")


def run(args: argparse.Namespace) -> int:
    logging.getLogger("usplat_dr.model.hypernet.resnet").setLevel(logging.ERROR)
    variants = ["baseline", "agnostic", "full"] if args.variant == "all" else [args.variant]
    for variant in variants:
        model = UniqueSplat.from_preset(args.preset, variant=variant)
        print(f"preset {args.preset!r}, variant {variant!r}")
        for name, count in model.parameter_table():
            print(f"  {name:<62} {count:>12,}")
        total = model.parameter_table()[-1][1]
        if args.preset == "paper" and variant == "full":
            print(f"  {'paper (UniqueSplat, full model)':<62} {PAPER_PARAMETERS:>12,.0f}"
                  f"  ({100 * (total / PAPER_PARAMETERS - 1):+.1f}%)")
    return 0
