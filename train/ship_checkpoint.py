"""Ship a trained model: export its weights (float16, no optimiser state) under checkpoints/,
evaluate the shipped file against the float32 original on a held-out synthetic set, and
record it in checkpoints/manifest.json.

    python train/ship_checkpoint.py --checkpoint outputs/tiny_depth/checkpoints/last.ckpt \
        --name tiny_baseline --eval-data outputs/big/test2000 \
        --train-command "usplat train --config ..." --data "480 scenes, seed 100"

A model fine-tuned with most of its weights frozen (the budget stage: an importance head on a
shipped model) ships as an add-on: ``--base tiny_full`` stores only the weights that differ
from the shipped tiny_full.pt, and ``--budgets 0.1 0.3`` adds the held-out metrics at those
fractions of the Gaussians (``rank_by="learned"``) to its manifest entry.
"""

import argparse
import hashlib
import json
import logging
import sys
import tempfile
from pathlib import Path

import usplat_dr  # noqa: F401  (libLLVM before drjit)
from usplat_dr import portable

portable.enable()  # AVX2 code paths, as the usplat command (before torch is imported)
from usplat_dr.evaluation import evaluate, synthetic_indices  # noqa: E402
from usplat_dr.io import write_json  # noqa: E402
from usplat_dr.training.checkpoints import (  # noqa: E402
    export_weights,
    load_model,
    read_usplat_checkpoint,
    resolve_checkpoint,
)

ROOT = Path(__file__).parents[1] / "checkpoints"
#: Float16 storage is accepted when it moves the held-out PSNR by at most this much.
HALF_TOLERANCE_DB = 0.01


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def held_out(checkpoint: Path, data: str, size: int, splits: list[str],
             trust: bool = False, budget=None) -> dict:
    model, _ = load_model(checkpoint, trust=trust)
    dataset = {"name": "synth", "roots": [data], "image_shape": [size, size]}
    with tempfile.TemporaryDirectory() as out:
        summary = evaluate(model, dataset, synthetic_indices(data, splits), out,
                           images_per_split=0, progress=False, budget=budget,
                           rank_by=None if budget is None else "learned")
    return summary["splits"]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True, type=Path, help="a usplat training checkpoint")
    p.add_argument("--name", required=True, help="manifest name and file stem")
    p.add_argument("--eval-data", required=True, help="held-out synthetic set (usplat synth)")
    p.add_argument("--train-command", required=True, help="the command that trained it")
    p.add_argument("--data", required=True, help="what it was trained on, in words")
    p.add_argument("--splits", nargs="+", default=None, help="splits to evaluate (all)")
    p.add_argument("--size", type=int, default=64, help="evaluation image size")
    p.add_argument("--root", type=Path, default=ROOT, help="checkpoints folder (with its "
                   "manifest.json)")
    p.add_argument("--base", default=None, help="ship an add-on: only the weights that "
                   "differ from this shipped checkpoint's (a name in the manifest)")
    p.add_argument("--budgets", type=float, nargs="+", default=[], help="also record the "
                   "standard split's metrics at these fractions of the Gaussians (learned)")
    p.add_argument("--trust-checkpoint", action="store_true", help="unpickle --checkpoint (and "
                   "its model.init_from) fully: for your own files written before checkpoints "
                   "held plain data only")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)

    trust = args.trust_checkpoint
    reference = held_out(args.checkpoint, args.eval_data, args.size, ["standard"], trust)
    file = args.root / f"{args.name}.pt"
    state = read_usplat_checkpoint(args.checkpoint, trust=trust)
    metadata = {"recipe": state["config"].get("loss", {}), "eval_data": args.eval_data}
    # Read before exporting: the init may be the very file this export replaces (a new stage
    # of tiny_baseline.pt trained from the previous one).
    init = state["config"]["model"].get("init_from")
    if init:  # a path, or a shipped checkpoint's name: recorded as the other entries' paths
        path = resolve_checkpoint(init)
        init = f"checkpoints/{path.name}" if path.parent.resolve() == ROOT.resolve() else str(path)
    init_steps = read_usplat_checkpoint(init, trust=trust)["step"] if init else 0
    manifest_path = args.root / "manifest.json"
    manifest = json.loads(manifest_path.read_text()) if manifest_path.is_file() else []
    shipped_init = next((e for e in manifest if init and Path(init).resolve()
                         == (args.root / e["file"]).resolve()), None)
    if shipped_init is not None:  # a shipped file: its own training counts every stage
        init_steps = shipped_init["steps"]
    export_weights(args.checkpoint, file, half=True, metadata=metadata, trust=trust,
                   base=args.base)
    shipped = held_out(file, args.eval_data, args.size, args.splits)
    diff = abs(shipped["standard"]["psnr"] - reference["standard"]["psnr"])
    half = diff <= HALF_TOLERANCE_DB
    if not half:
        export_weights(args.checkpoint, file, half=False, metadata=metadata, trust=trust,
                       base=args.base)
        shipped = held_out(file, args.eval_data, args.size, args.splits)
    cfg = state["model_config"]
    entry = {"name": args.name, "preset": state["config"]["model"].get("preset", "tiny"),
             "variant": cfg["variant"], "file": file.name, "sha256": sha256(file),
             "train_command": args.train_command, "data": args.data,
             "steps": init_steps + state["step"],
             "init_from": init, "finetune_steps": state["step"] if init else None,
             "storage": "float16" if half else "float32",
             "float16_psnr_change_db": round(diff, 4),
             "provenance": state.get("provenance", {}),
             "metrics": {"eval_data": args.eval_data, "splits": shipped}}
    if state.get("depth_range") is not None:  # render/view warn outside it
        entry["depth_range"] = state["depth_range"]
    if args.base:
        entry["base"] = args.base
    if args.budgets:
        # (where each budget goes is the evaluation's allocation, left out: NaN where a
        # material is absent, which strict JSON readers refuse)
        entry["metrics"]["budgets"] = {
            str(k): {key: v for key, v in held_out(file, args.eval_data, args.size, ["standard"],
                                                   budget=k)["standard"].items()
                     if key != "allocation"}
            for k in args.budgets}
    manifest = [e for e in manifest if e["name"] != args.name] + [entry]
    write_json(manifest_path, manifest)
    std = shipped["standard"]
    print(f"{args.name}: {file} ({file.stat().st_size / 2**20:.1f} MiB, {entry['storage']}; "
          f"float16 moved PSNR by {diff:.4f} dB): standard PSNR {std['psnr']:.2f} dB, "
          f"SSIM {std['ssim']:.3f}, AbsRel {std['abs_rel']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
