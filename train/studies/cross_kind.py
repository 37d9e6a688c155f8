"""The cross-kind shift: (a) trained on one scene kind, evaluated on every kind, against (a)
trained on that kind (the paper's cross-dataset table in miniature: RealEstate10K -> indoor,
ACID -> outdoor, DTU -> objects).

    python train/studies/cross_kind.py --eval-data outputs/big/test2000 --out outputs/cross_kind \\
        --model indoor=outputs/kind_indoor/checkpoints/last.ckpt \\
        --model object=outputs/kind_object/checkpoints/last.ckpt \\
        --model outdoor=outputs/kind_outdoor/checkpoints/last.ckpt [--source indoor]

Evaluates each model once on the standard split (one thread, resumable: a model already
evaluated in ``<out>/<kind>`` is read back), then writes ``<out>/cross_kind.md`` and ``.json``:
mean PSNR and depth AbsRel per (trained on, evaluated on) kind, and for each kind K other than
``--source`` the shift, (a)-source minus (a)-K on K's scenes, paired by scene with a bootstrap
95% interval. The shift counts when it is <= -3 dB.
"""

import argparse
import csv
from pathlib import Path

import usplat_dr  # noqa: F401  (libLLVM before drjit)
from usplat_dr import portable

portable.enable()  # AVX2 code paths, as the usplat command (before torch is imported)

KINDS = ("indoor", "outdoor", "object")
SHIFT = -3.0  # dB: the shift counts at or below this


def model_arg(text: str) -> tuple[str, str]:
    kind, _, path = text.partition("=")
    if kind not in KINDS or not path:
        raise argparse.ArgumentTypeError(f"KIND=CHECKPOINT with KIND one of {KINDS}, got "
                                         f"{text!r}")
    return kind, path


def evaluated(kind: str, checkpoint: str, data: str, out: Path) -> dict:
    """scene -> {psnr, abs_rel} of the model on the standard split (evaluated once)."""
    import drjit as dr
    import torch

    from usplat_dr.evaluation import evaluate, synthetic_indices
    from usplat_dr.training.checkpoints import load_model, training_image_shape

    folder = out / kind
    table = folder / "per_scene.csv"
    if not table.is_file():
        torch.set_num_threads(1)
        dr.set_thread_count(1)
        model, _ = load_model(checkpoint)
        shape = training_image_shape(checkpoint) or (64, 64)
        index = synthetic_indices(data, ["standard"])
        evaluate(model, {"name": "synth", "roots": [data], "image_shape": list(shape)},
                 index, folder, images_per_split=2, progress=False, label=f"(a)-{kind}")
    with open(table) as f:
        return {r["scene"]: {"psnr": float(r["psnr"]), "abs_rel": float(r["abs_rel"])}
                for r in csv.DictReader(f) if r["split"] == "standard"}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", type=model_arg, action="append", required=True,
                   metavar="KIND=CHECKPOINT", help="(a) trained on KIND only (repeat)")
    p.add_argument("--eval-data", required=True, help="a held-out `usplat synth` set of all kinds")
    p.add_argument("--source", default="indoor", choices=KINDS,
                   help="the kind the cross-kind verdict trains on")
    p.add_argument("--out", default="outputs/cross_kind")
    args = p.parse_args(argv)
    import numpy as np

    from usplat_dr.evaluation.verdict import bootstrap_interval
    from usplat_dr.io import write_json

    models = dict(args.model)
    if args.source not in models:
        p.error(f"--source {args.source}: give its model with --model {args.source}=...")
    out = Path(args.out)
    results = {k: evaluated(k, ckpt, args.eval_data, out) for k, ckpt in models.items()}
    kinds = [k for k in KINDS if any(s.startswith(f"{k}_") for s in results[args.source])]
    cells = {}
    for trained, scenes in results.items():
        for k in kinds:
            rows = [v for s, v in scenes.items() if s.startswith(f"{k}_")]
            cells[(trained, k)] = {m: float(np.nanmean([r[m] for r in rows])) for m in
                                   ("psnr", "abs_rel")} | {"scenes": len(rows)}
    lines = [(f"(a) trained on one kind, evaluated on `{args.eval_data}` (standard split): "
             "PSNR dB / depth AbsRel, mean over each kind's scenes"), "",
             "| trained on \\ evaluated on | " + " | ".join(kinds) + " |",
             "|---|" + "---|" * len(kinds)]
    for trained in models:
        lines.append(f"| {trained} | " + " | ".join(
            f"{cells[(trained, k)]['psnr']:.2f} / {cells[(trained, k)]['abs_rel']:.3f}"
            for k in kinds) + " |")
    shifts = {}
    for k in kinds:
        if k == args.source or k not in models:
            continue
        keys = sorted(s for s in results[k] if s.startswith(f"{k}_") and s in results[args.source])
        d = np.array([[results[args.source][s]["psnr"] - results[k][s]["psnr"] for s in keys]])
        low, high = bootstrap_interval(d)
        shifts[k] = {"mean": float(d.mean()), "low": low, "high": high, "scenes": len(keys),
                     "counts": bool(d.mean() <= SHIFT)}
    lines += ["", (f"Shift, (a)-{args.source} minus (a)-K on K's scenes (paired by scene, "
              f"bootstrap 95%; counts at <= {SHIFT:+.0f} dB):"), ""]
    lines += [f"- {k}: {v['mean']:+.2f} dB [{v['low']:+.2f}, {v['high']:+.2f}] over "
              f"{v['scenes']} scenes: {'counts' if v['counts'] else 'does not count'}"
              for k, v in shifts.items()]
    text = "\n".join(lines) + "\n"
    write_json(out / "cross_kind.json", {
        "eval_data": args.eval_data, "models": models, "source": args.source,
        "cells": {f"{t}->{k}": v for (t, k), v in cells.items()}, "shifts": shifts})
    (out / "cross_kind.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
