"""What near/far from sparse points costs: ``usplat import`` and ``render --images`` set a
scene's depth range from its COLMAP points (``usplat_dr.data.importers.near_far_from_points``:
percentiles of the points' depths, widened) when the user gives none. On a synthetic set with
known depth, this script makes the points an SfM run would (a random sample of the surfaces
the frames see, from the true depth maps), applies each candidate rule, and renders the
standard split with the range each gives against the scene's own range, per scene kind.

    python train/studies/near_far_rule.py --checkpoint tiny_full --data outputs/big/test2000 \\
        --out outputs/near_far

Writes ``per_scene.csv`` (the range and PSNR per rule and scene) and ``summary.json`` (per
rule and kind: PSNR minus the scene's own range's, mean and 95% t interval over scenes), and
prints the table. A rule maps the depths of the points the cameras see to (near, far):
percentiles widened by factors (the importer's form), or the depths' geometric mean divided
and multiplied by a factor (a fixed far/near ratio, centred on the scene).
"""

import argparse
import csv
import json
from pathlib import Path

import numpy as np
import torch

import usplat_dr  # noqa: F401  (libLLVM first)
from usplat_dr.data.chunks import cameras_to_matrices, read_chunk, stage_chunks
from usplat_dr.data.dataset import dataset_from_section
from usplat_dr.data.importers import visible_depths
from usplat_dr.data.types import model_inputs
from usplat_dr.evaluation.metrics import psnr
from usplat_dr.evaluation.verdict import t_interval
from usplat_dr.io import atomic_open, write_json
from usplat_dr.training.loader import load


def _percentiles(plo: float, phi: float, mlo: float, mhi: float):
    def rule(d: np.ndarray) -> tuple[float, float]:
        lo, hi = np.percentile(d, [plo, phi])
        return float(lo * mlo), float(hi * mhi)
    return rule


def _ratio(k: float):
    def rule(d: np.ndarray) -> tuple[float, float]:
        centre = float(np.exp(np.log(d).mean()))
        return centre / k, centre * k
    return rule


#: The candidate rules; the first is the importer's default (``near_far_from_points``).
RULES = {"p1-99 x0.8/1.2": _percentiles(1, 99, 0.8, 1.2),
         "p0-100 x0.8/1.2": _percentiles(0, 100, 0.8, 1.2),
         "p1-99 x0.5/2": _percentiles(1, 99, 0.5, 2.0),
         "p1-99 x0.8/3": _percentiles(1, 99, 0.8, 3.0),
         "mean /3 x3": _ratio(3.0), "mean /10 x10": _ratio(10.0)}


def sfm_points(scene: dict, count: int, rng: np.random.Generator) -> np.ndarray:
    """[N, 3] world points: ``count`` pixels drawn at random over all frames where the true
    depth is finite, back-projected with the frame's camera (what the frames see, as SfM
    triangulates it; no noise)."""
    c2w, k = (t.double().numpy() for t in cameras_to_matrices(scene["cameras"]))
    depth = scene["depths"].double().numpy()  # [V, H, W] camera-space z, +inf on a miss
    _, h, w = depth.shape
    valid = np.argwhere(np.isfinite(depth) & (depth > 0))
    pick = valid[rng.choice(len(valid), size=min(count, len(valid)), replace=False)]
    f, y, x = pick.T
    z = depth[f, y, x]
    u, vv = (x + 0.5) / w, (y + 0.5) / h
    cam = np.stack([(u - k[f, 0, 2]) / k[f, 0, 0] * z, (vv - k[f, 1, 2]) / k[f, 1, 1] * z, z], 1)
    return np.einsum("nij,nj->ni", c2w[f, :3, :3], cam) + c2w[f, :3, 3]


def rule_range(points: np.ndarray, c2w: np.ndarray, k: np.ndarray, rule) -> tuple:
    """``rule`` on the depths of the points each camera sees, over all cameras (the
    importer's selection, ``near_far_from_points``)."""
    return rule(visible_depths(points, c2w, k))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default="tiny_full")
    p.add_argument("--data", required=True, help="a `usplat synth` test root (with depths)")
    p.add_argument("--out", required=True)
    p.add_argument("--points", type=int, default=2000, help="sparse points per scene")
    p.add_argument("--scenes", type=int, default=60)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    records = {s["key"]: s for c in stage_chunks([args.data], "test")
               for s in read_chunk(c)}
    model = load(args.checkpoint)
    ds = dataset_from_section({"name": "synth", "roots": [args.data], "image_shape": [64, 64],
                               "evaluation_index": str(Path(args.data)
                                                       / "evaluation_index_standard.json")},
                              "test")
    rows = []
    for i, example in enumerate(ds):
        if i == args.scenes:
            break
        scene = records[example["scene"]]
        c2w, k = (t.double().numpy() for t in cameras_to_matrices(scene["cameras"]))
        points = sfm_points(scene, args.points, rng)
        batch = torch.utils.data.default_collate([example])
        gt = batch["target"]["image"][0]
        own = (float(batch["context"]["near"][0, 0]), float(batch["context"]["far"][0, 0]))
        ranges = {"own": own, **{name: rule_range(points, c2w, k, r)
                                 for name, r in RULES.items()}}
        row = {"scene": example["scene"], "kind": example["scene"].split("_")[0]}
        for name, (near, far) in ranges.items():
            b = {**batch, "context": {**batch["context"],
                                      "near": torch.full_like(batch["context"]["near"], near),
                                      "far": torch.full_like(batch["context"]["far"], far)}}
            with torch.no_grad():
                pred = model(*model_inputs(b)).color[0]
            row[f"{name} near"], row[f"{name} far"] = near, far
            row[f"{name} psnr"] = float(psnr(pred, gt).mean())
        rows.append(row)
        print(f"[{i + 1}] {row['scene']}: own {own[0]:.3g}-{own[1]:.3g} "
              + ", ".join(f"{n} {row[f'{n} near']:.3g}-{row[f'{n} far']:.3g} "
                          f"{row[f'{n} psnr'] - row['own psnr']:+.2f} dB" for n in RULES),
              flush=True)
    with atomic_open(out / "per_scene.csv", "w") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    summary = {}
    for name in RULES:
        for kind in ["all", *sorted({r["kind"] for r in rows})]:
            d = [r[f"{name} psnr"] - r["own psnr"] for r in rows if kind in ("all", r["kind"])]
            lo, hi = t_interval(d)
            summary.setdefault(name, {})[kind] = {"mean_db": float(np.mean(d)), "low": lo,
                                                  "high": hi, "scenes": len(d)}
    write_json(out / "summary.json", {"args": vars(args), "rules": list(RULES),
                                      "delta": summary})
    kinds = ["all", *sorted({r["kind"] for r in rows})]
    print("| rule | " + " | ".join(kinds) + " |\n|---|" + "---|" * len(kinds))
    for name in RULES:
        print(f"| {name} | " + " | ".join(
            f"{summary[name][k]['mean_db']:+.2f} [{summary[name][k]['low']:+.2f}, "
            f"{summary[name][k]['high']:+.2f}]" for k in kinds) + " |")
    print(json.dumps({"out": str(out)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
