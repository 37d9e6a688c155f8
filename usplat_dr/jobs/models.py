"""``usplat models``: the shipped models, one line each (name, variant, size, purpose, the
commands it is the default of, sha256 prefix); ``--all`` adds the study models."""

import argparse

from usplat_dr.training import registry


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--all", action="store_true",
                   help="also the study models (study/NAME: the studies' arms, controls and "
                   "add-ons; loadable by name, never a default)")


def run(args: argparse.Namespace) -> int:
    models = registry.shipped_models(registry.CHECKPOINTS)  # read here: tests point it away
    if not models:
        raise FileNotFoundError(f"no shipped models in {registry.CHECKPOINTS} (manifest.json): a "
                                f"wheel without package data, or a checkout without "
                                f"checkpoints/")
    shown = [m for m in models.values() if args.all or m.kind == "user"]
    for model in shown:
        print(model.line())
    hidden = len(models) - len(shown)
    if hidden:
        print(f"({hidden} study models: usplat models --all)")
    return 0
