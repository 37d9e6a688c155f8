"""``usplat eval``: evaluate a trained model with the field's protocol (per-scene CSV, summary
JSON, renders)."""

import argparse
import json
import logging
import os

import torch

from usplat_dr.evaluation import evaluate, synthetic_indices
from usplat_dr.evaluation.lpips import LPIPS
from usplat_dr.evaluation.protocol import copy_line
from usplat_dr.jobs.arguments import (
    CHECKPOINT_HELP,
    DATASET_HELP,
    DATASETS,
    DEVICE_HELP,
    add_budget_arguments,
    add_image_shape_argument,
    add_near_far_arguments,
    add_trust_argument,
    budget_from_args,
    check_budget_arguments,
    dataset_section,
    fit_checkpoint,
    out_folder,
)
from usplat_dr.render.prune import PruneSettings
from usplat_dr.training.checkpoints import checkpoint_provenance
from usplat_dr.training.loader import load

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP)
    p.add_argument("--data", required=True, help="dataset root (chunk format)")
    p.add_argument("--dataset", default="synth", choices=DATASETS,
                   help=DATASET_HELP)
    p.add_argument("--index", nargs="+", metavar="SPLIT=PATH",
                   help="evaluation index JSON(s); default: the synthetic set's own splits")
    p.add_argument("--splits", nargs="+", help="synthetic splits to evaluate (default: all)")
    add_image_shape_argument(p)
    add_near_far_arguments(p, "each scene's recorded range")
    add_trust_argument(p)
    p.add_argument("--prune", action="store_true",
                   help="prune the Gaussians per target view before rendering (exact culling "
                   "+ merging near-duplicates, within 0.05 dB): fewer Gaussians, but on CPU "
                   "slower at every size measured (train/bench/README.md, \"Pruning that pays\"); "
                   "off by default")
    add_budget_arguments(p)
    p.add_argument("--precision", default="float32", choices=["float32", "bfloat16"],
                   help="the networks' inference precision (bfloat16: torch autocast, faster "
                        "on CPUs with AVX-512-BF16 or AMX; geometry and rendering stay "
                        "float32; train/bench/README.md, \"bfloat16 inference\")")
    p.add_argument("--lpips-vgg", help="torchvision vgg16-397923af.pth (for LPIPS)")
    p.add_argument("--lpips-lin", help="lpips/weights/v0.1/vgg.pth (for LPIPS)")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                   help=DEVICE_HELP)
    p.add_argument("--out", type=out_folder, default="outputs/eval",
                   help="the results folder (summary.json, per_scene.csv, renders)")


def warn_slow_bfloat16() -> None:
    """bfloat16 pays on the CPU only with native bfloat16 instructions (AVX-512-BF16, AMX)
    that oneDNN may use: capped at AVX2 (the portable pin, which ``usplat`` leaves off for
    bfloat16 unless the environment sets it), the tiny model at 64x64 took 2.08 s per scene in
    bfloat16 against 0.15 s in float32 (0.07 s natively)."""
    if os.environ.get("ONEDNN_MAX_CPU_ISA", "").upper() == "AVX2":
        log.warning("--precision bfloat16 with ONEDNN_MAX_CPU_ISA=AVX2 runs oneDNN's AVX2 "
                    "code, which has no bfloat16 instructions: about 14x slower than float32. "
                    "Unset it for the fast path.")
    elif not _onednn_has_bfloat16():
        log.warning("--precision bfloat16: this CPU has no bfloat16 instructions oneDNN can "
                    "use; expect it to be slower than float32")


def _onednn_has_bfloat16() -> bool:
    """Whether oneDNN can use bfloat16 instructions here (a private torch op: False when it
    is missing in this build)."""
    try:
        return bool(torch.backends.mkldnn.is_available()
                    and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def run(args: argparse.Namespace) -> int:
    check_budget_arguments(args)
    indices = None
    if args.index:
        bad = [i for i in args.index if "=" not in i or not all(i.split("=", 1))]
        if bad:
            raise ValueError(f"--index takes SPLIT=PATH (e.g. standard=assets/"
                             f"evaluation_index_re10k.json), got {bad[0]!r}")
        indices = dict(item.split("=", 1) for item in args.index)
    if indices is None:
        indices = synthetic_indices(args.data, args.splits)
        if not indices:
            raise FileNotFoundError(f"--data: no evaluation_index_*.json with scenes in "
                                    f"{args.data}; pass --index NAME=PATH (e.g. "
                                    f"standard=assets/evaluation_index_re10k.json)")
    fit_checkpoint(args)
    lpips = None
    if args.lpips_vgg or args.lpips_lin:
        lpips = LPIPS.from_files(args.lpips_vgg, args.lpips_lin).to(args.device)
    model = load(args.checkpoint, args.device, args.trust_checkpoint)
    model.inference_precision = args.precision
    if args.precision == "bfloat16" and args.device == "cpu":
        warn_slow_bfloat16()
    dataset = dataset_section(args)
    # Scenes the checkpoint trained on are warned about (checkpoints that record no
    # train_keys, from before they were recorded, cannot be checked).
    record = checkpoint_provenance(args.checkpoint, args.trust_checkpoint)
    summary = evaluate(model, dataset, indices, args.out, lpips=lpips, device=args.device,
                       prune=PruneSettings(merge=True) if args.prune else None,
                       provenance=record,
                       budget=budget_from_args(args))
    print(json.dumps(summary, indent=1))
    for split, metrics in summary["splits"].items():  # the margin over the trivial predictor
        if metrics["scenes"]:
            print(copy_line(split, metrics))
    if not any(split["scenes"] for split in summary["splits"].values()):
        first = next(iter(summary["splits"].items()))
        raise ValueError(f"--data {args.data}: no scene was scored ({first[0]}: "
                         f"{first[1]['coverage']}): the evaluation indices name scenes the "
                         f"data do not hold, or every scene was skipped (the warnings above "
                         f"say why)")
    return 0
