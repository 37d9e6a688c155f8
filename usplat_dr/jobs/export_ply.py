"""``usplat export-ply``: the Gaussians predicted for one target view, as a standard 3DGS
PLY (``--gaussians K``: the K the budget keeps)."""

import argparse

import torch

from usplat_dr.data.types import model_inputs
from usplat_dr.jobs.arguments import (
    add_example_arguments,
    add_near_far_arguments,
    budget_from_args,
    check_budget_arguments,
    check_near_far,
    fit_checkpoint,
    non_negative_int,
    one_example,
    out_file,
)
from usplat_dr.model.ply import write_ply


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_example_arguments(p)
    p.add_argument("--target", type=non_negative_int, default=0, help="target view index")
    add_near_far_arguments(p, "the scene's recorded range")
    p.add_argument("--min-opacity", type=float, default=0.0,
                   help="leave out Gaussians below this opacity")
    p.add_argument("--out", type=out_file, default="outputs/export/gaussians.ply",
                   help="the PLY file to write")


def run(args: argparse.Namespace) -> int:
    check_budget_arguments(args)
    check_near_far(args)
    fit_checkpoint(args)
    model, batch = one_example(args)
    with torch.no_grad():
        out = model(*model_inputs(batch, torch.device(args.device)), render=False,
                    budget=budget_from_args(args))
    n = out.num_targets
    if not 0 <= args.target < n:
        raise ValueError(f"--target must be in 0..{n - 1} (the scene's target views), got "
                         f"{args.target}")
    path = write_ply(args.out, out.target(0, args.target), min_opacity=args.min_opacity)
    kept = "" if args.gaussians is None else f" ({int(out.aux['kept'][0, args.target])} kept)"
    if "auto_keep" in out.aux:
        kept = (kept[:-1] + f", {float(out.aux['auto_keep'][0]):.0%} chosen by the automatic "
                "count; the PLY holds them before the render's merging)")
    print(f"wrote {path}: the Gaussians predicted for target {args.target} of "
          f"{batch['scene'][0]}{kept}")
    return 0
