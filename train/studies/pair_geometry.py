"""The geometry of context pairs: baseline over depth and relative rotation, for a synthetic
training set (pairs the view sampler draws) and for a posed capture (the study's pairs).

``python train/studies/pair_geometry.py --synthetic outputs/photo/train200/train --gaps 5 10
--capture monstree=outputs/pose/monstree/sparse --out pair_geometry.json``

Baseline over depth is the distance between the two camera centres divided by the mean of the
two views' median depths: for synthetic scenes the median of the ground-truth depth map, for a
capture the median camera-space z of the sparse points in front of the camera (COLMAP's unit
cancels). The rotation is the angle of R_i^T R_j.
"""

import argparse
import json
import platform
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from usplat_dr.data.user_views import read_cameras


def angle_deg(c2w_i: np.ndarray, c2w_j: np.ndarray) -> float:
    r = c2w_i[:3, :3].T @ c2w_j[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))))


def pair_row(c2w: np.ndarray, depth: np.ndarray, i: int, j: int) -> tuple[float, float]:
    baseline = float(np.linalg.norm(c2w[i, :3, 3] - c2w[j, :3, 3]))
    return baseline / float((depth[i] + depth[j]) / 2), angle_deg(c2w[i], c2w[j])


def synthetic_pairs(root: Path, gaps: list[int], stride: int = 3) -> dict[str, list]:
    """Per scene kind, (baseline/depth, degrees) of the pairs (i, i + g) every ``stride``
    frames, for every gap g in ``gaps``."""
    out = defaultdict(list)
    for chunk in sorted(root.glob("*.torch")):
        for ex in torch.load(chunk, weights_only=False):
            cams = ex["cameras"].double().numpy()
            w2c = np.tile(np.eye(4), (len(cams), 1, 1))
            w2c[:, :3] = cams[:, 6:].reshape(-1, 3, 4)
            c2w = np.linalg.inv(w2c)
            d = ex["depths"].float().numpy().reshape(len(cams), -1)
            depth = np.array([np.median(v[np.isfinite(v)]) for v in d])
            for g in gaps:
                for i in range(0, len(cams) - g, stride):
                    out[ex["key"].split("_")[0]].append(pair_row(c2w, depth, i, i + g))
    return out


def capture_pairs(model: Path, gaps: list[int], stride: int = 3) -> list:
    scene = read_cameras(model, ignore_distortion=True)
    if scene.points is None:
        raise ValueError(f"{model}: the capture's depth needs COLMAP's sparse points")
    c2w = scene.extrinsics
    depth = []
    for m in c2w:
        z = (np.c_[scene.points, np.ones(len(scene.points))] @ np.linalg.inv(m).T)[:, 2]
        depth.append(np.median(z[z > 0]))
    depth = np.array(depth)
    return [pair_row(c2w, depth, i, i + g) for g in gaps for i in range(0, len(c2w) - g, stride)]


def describe(rows: list) -> dict:
    a = np.array(rows)
    q = lambda v: [round(float(x), 3) for x in np.percentile(v, [10, 50, 90])]  # noqa: E731
    return {"pairs": len(a), "baseline_over_depth_p10_p50_p90": q(a[:, 0]),
            "degrees_p10_p50_p90": q(a[:, 1])}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--synthetic", type=Path, help="a folder of training chunks (*.torch)")
    p.add_argument("--gaps", type=int, nargs="+", default=[5, 10],
                   help="synthetic frame gaps (the view sampler's range)")
    p.add_argument("--capture", action="append", default=[], metavar="NAME=COLMAP_MODEL")
    p.add_argument("--capture-gaps", type=int, nargs="+", default=[2, 4],
                   help="the real-photo study's gaps")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    result = {"command": "python train/studies/pair_geometry.py", "machine": platform.machine(),
              "date": time.strftime("%Y-%m-%d"), "synthetic": {}, "captures": {}}
    if args.synthetic:
        for kind, rows in sorted(synthetic_pairs(args.synthetic, args.gaps).items()):
            result["synthetic"][kind] = describe(rows)
    for spec in args.capture:
        name, _, model = spec.partition("=")
        result["captures"][name] = describe(capture_pairs(Path(model), args.capture_gaps))
    text = json.dumps(result, indent=1)
    print(text)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(text)
    tmp.replace(args.out)


if __name__ == "__main__":
    main()
