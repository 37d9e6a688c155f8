"""The gauge's manipulation check: does a model's prediction depend on the unit its cameras come
in? For each model and each held-out scene of ``--root``'s standard split, the same images
predicted with the true cameras, with the world scaled about its origin by each ``--scales``
factor (camera centres and near/far; the images are the same), and with the two context
images swapped (correspondence: a model that reads it loses). PSNR against the target
photos and AbsRel of the depth (divided by the factor back into the true unit) against the
ground truth, mean over scenes, and each condition minus the true cameras' paired over
scenes; written to ``--out`` (JSON) and printed.

Run (one thread): ``USPLAT_THREADS=1 python train/studies/gauge_check.py --root /tmp/t5000
--models tiny_full,gauge=outputs/photo/ft_gauge/checkpoints/last.ckpt --out
train/studies/real_photos/gauge_check.json``.
"""

import argparse
import json
import os
import platform
import sys
import time

import numpy as np
import torch

import usplat_dr
from usplat_dr.evaluation.metrics import psnr
from usplat_dr.evaluation.protocol import held_out_scenes, load_example


def conditions(scales: list[float]) -> list[tuple[str, float, bool]]:
    """(label, factor, images swapped) of each condition, the true cameras first."""
    return ([("true", 1.0, False)] + [(f"scale {s:g}", s, False) for s in scales]
            + [("context swapped", 1.0, True)])


def scene_scores(model, example, factor: float, swap: bool) -> tuple[float, float]:
    """(PSNR, AbsRel) of ``model`` on one example in a world scaled by ``factor``."""
    c, t = example["context"], example["target"]
    ext, text = c["extrinsics"][0].clone(), t["extrinsics"][0].clone()
    ext[:, :3, 3] *= factor
    text[:, :3, 3] *= factor
    images = c["image"][0].flip(0) if swap else c["image"][0]
    p = model.predict(images, intrinsics=c["intrinsics"][0], extrinsics=ext,
                      target_intrinsics=t["intrinsics"][0], target_extrinsics=text,
                      near=float(c["near"][0, 0]) * factor, far=float(c["far"][0, 0]) * factor)
    gt = t["depth"][0]
    valid = gt > 0
    absrel = ((p.depth / factor - gt).abs()[valid] / gt[valid]).mean()
    return float(psnr(p.color, t["image"][0]).mean()), float(absrel)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--root", required=True, help="a usplat synth test set")
    p.add_argument("--models", required=True,
                   help="comma-separated shipped names or label=checkpoint path")
    p.add_argument("--scales", nargs="+", type=float, default=[3.0, 1 / 3])
    p.add_argument("--size", type=int, default=64)
    p.add_argument("--out", required=True)
    args = p.parse_args()
    dataset, index, scenes = held_out_scenes(args.root, size=args.size)
    examples = [load_example(dataset, index, s) for s in scenes]
    result = {"command": "python " + " ".join(sys.argv),
              "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
              "date": time.strftime("%Y-%m-%d", time.gmtime()), "scenes": len(scenes),
              "models": {}}
    for entry in args.models.split(","):
        label, _, path = entry.partition("=")
        model = usplat_dr.load(path or label)
        rows = {}
        for name, factor, swap in conditions(args.scales):
            with torch.no_grad():
                rows[name] = np.array([scene_scores(model, ex, factor, swap) for ex in examples])
        true = rows["true"]
        out = {}
        for name, a in rows.items():
            out[name] = {"psnr": float(a[:, 0].mean()), "absrel": float(a[:, 1].mean()),
                         "psnr_minus_true": float((a[:, 0] - true[:, 0]).mean()),
                         "psnr_minus_true_max_abs": float(np.abs(a[:, 0] - true[:, 0]).max())}
            print(f"{label:12s} {name:16s} PSNR {out[name]['psnr']:6.2f} "
                  f"({out[name]['psnr_minus_true']:+.3f}) AbsRel {out[name]['absrel']:.3f}")
        result["models"][label] = out
    with open(args.out + ".tmp", "w") as f:
        json.dump(result, f, indent=1)
    os.replace(args.out + ".tmp", args.out)


if __name__ == "__main__":
    main()
