"""Real photographs: each model against copying the nearest context photo, on captures posed by
``usplat pose``, and depth on a real stereo pair against its ground truth and a plane sweep.

For every capture under ``--realdata`` (posed into ``--pose-root``/<capture>, reused when the
photos have not changed), the registered photos in name order (the order they were taken), at
each ``--sizes`` (square crops, as ``usplat render --images`` makes them):

- pairs (i, i + g) for the gaps ``GAPS``, every ``STRIDE`` photos; targets *between* (the
  photos strictly inside the pair) and *beyond* (the photo before and the one after);
- each model predicts every target from the pair (near/far from the capture's sparse points),
  copying predicts it as the context photo whose centre is nearest, and a classical plane
  sweep renders it from the pair (``sweep_render``, exploratory: added after the
  pre-registration); PSNR of each against
  the real photo, per target (``rows.csv``), and the means per capture, size, placement and
  model with the margin over copying (``summary.json``, printed);
- a contact sheet per capture and size (``sheet_<capture>_<size>.png``): context photos, the
  target, copying and each model.

The stereo pair (``skimage.data.stereo_motorcycle()``: Middlebury 2014, its calibration in the
docstring): both views as context, the left as the target; each model's depth and a 7x7-SAD
plane sweep (``usplat_dr.geometry.plane_sweep``, 128 hypotheses uniform in inverse depth over
``MOTO_RANGE``) at the same size against the ground truth Z = f B / (d + doffs), AbsRel on the
pixels with ground truth (``depth.csv``).

Run (one thread): ``USPLAT_THREADS=1 python train/studies/real_photos.py --out
train/studies/real_photos --models 64:tiny_baseline,tiny_full 128:tiny_baseline_128,
tiny_full_128``.
"""

import argparse
import csv
import json
import math
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

import usplat_dr
from usplat_dr.data.pose import PoseSettings, photos_in, pose_photos, posed_before
from usplat_dr.data.shims import covering_size, cropped_intrinsics, rescale_and_crop
from usplat_dr.data.user_views import context_views, read_cameras
from usplat_dr.evaluation.baselines import copy_nearest
from usplat_dr.evaluation.metrics import psnr
from usplat_dr.geometry.plane_sweep import plane_sweep, sweep_render

#: Context pairs: photo i with photo i + g for each gap, every STRIDE photos.
GAPS, STRIDE = (2, 4), 3
#: Depth hypotheses of the classical novel view (``sweep_views``).
SWEEP_DEPTHS = 64
#: The motorcycle's depth range given to the models and swept (metres; ground truth 2.1-5.0).
MOTO_RANGE = (1.5, 10.0)
#: skimage's calibration of the down-sampled pair (its docstring).
MOTO_F, MOTO_CX, MOTO_CY, MOTO_DOFFS, MOTO_BASELINE = 994.978, 311.193, 254.877, 31.086, 0.193001


def pairs(n: int, gaps: tuple[int, ...] = GAPS) -> list[tuple[int, int, list[int], list[int]]]:
    """(i, j, between, beyond) for ``n`` photos in capture order."""
    out = []
    for g in gaps:
        for i in range(0, n - g, STRIDE):
            j = i + g
            beyond = [k for k in (i - 1, j + 1) if 0 <= k < n]
            out.append((i, j, list(range(i + 1, j)), beyond))
    return out


def pose_capture(folder: Path, out: Path):
    photos = photos_in(folder)
    result = posed_before(photos, out)
    if result is None:
        result = pose_photos(photos, out, PoseSettings(threads=1), progress=False)
    print(f"{folder.parent.name}: {result.line()}", flush=True)
    return result


def load_model(name: str):
    return usplat_dr.load(name)


def capture_rows(capture: str, result, size: int, models: dict, sheet_pairs: int = 3,
                 gaps: tuple[int, ...] = GAPS):
    scene = read_cameras(str(result.model))
    paths = [str(p) for p in scene.image_paths]
    views = context_views(paths, scene, (size, size))
    images = views.images.float() / 255.0
    e, k = views.extrinsics, views.intrinsics
    rows, sheet = [], []
    for n, (i, j, between, beyond) in enumerate(pairs(len(paths), gaps)):
        ctx = [i, j]
        for placement, targets in (("between", between), ("beyond", beyond)):
            if not targets:
                continue
            gt = images[targets]
            copy = copy_nearest(images[ctx], e[ctx], e[targets])
            preds = {"copy": copy, "plane sweep": sweep_views(images, k, e, ctx, targets,
                                                                 views.near, views.far)}
            for name, model in models.items():
                preds[name] = model.predict(images[ctx], intrinsics=k[ctx], extrinsics=e[ctx],
                                            target_intrinsics=k[targets],
                                            target_extrinsics=e[targets], near=views.near,
                                            far=views.far).color
            baseline = float(np.linalg.norm(e[i, :3, 3] - e[j, :3, 3]))
            for name, pred in preds.items():
                for t, value in zip(targets, psnr(pred, gt).tolist()):
                    rows.append({"capture": capture, "size": size, "pair": f"{i}-{j}",
                                 "gap": j - i, "baseline": round(baseline, 4),
                                 "placement": placement, "target": t,
                                 "target_name": Path(paths[t]).name, "predictor": name,
                                 "psnr": round(value, 4)})
            if placement == "between" and len(sheet) < sheet_pairs and n % 2 == 0:
                cells = [images[i], images[j], gt[0]] + [p[0] for p in preds.values()]
                sheet.append(torch.cat(cells, dim=2))
    return rows, sheet, views.near, views.far


def sweep_views(images, k, e, ctx, targets, near, far) -> torch.Tensor:
    """Each target rendered classically from the pair (``sweep_render``, ``SWEEP_DEPTHS``
    hypotheses uniform in inverse depth over near/far)."""
    a = [images[i].permute(1, 2, 0).double().numpy() for i in ctx]
    depths = 1.0 / np.linspace(1.0 / near, 1.0 / far, SWEEP_DEPTHS)
    out = [sweep_render(a, [k[i].double().numpy() for i in ctx],
                        [e[i].double().numpy() for i in ctx], k[t].double().numpy(),
                        e[t].double().numpy(), tuple(images.shape[-2:]), depths)
           for t in targets]
    return torch.from_numpy(np.stack(out)).permute(0, 3, 1, 2).float()


def save_sheet(rows_of_cells: list[torch.Tensor], labels: list[str], path: Path) -> None:
    if not rows_of_cells:
        return
    grid = torch.cat(rows_of_cells, dim=1).permute(1, 2, 0).clamp(0, 1).numpy()
    tmp = path.with_suffix(".tmp.png")
    Image.fromarray((grid * 255 + 0.5).astype(np.uint8)).save(tmp)
    os.replace(tmp, path)
    path.with_suffix(".txt").write_text("columns: " + ", ".join(labels) + "\n")


def motorcycle_depth(size: int, models: dict) -> list[dict]:
    import skimage.data

    left, right, disp = skimage.data.stereo_motorcycle()
    h, w = left.shape[:2]
    k_l = torch.tensor([[MOTO_F / w, 0, MOTO_CX / w], [0, MOTO_F / h, MOTO_CY / h], [0, 0, 1]],
                       dtype=torch.float32)
    k_r = k_l.clone()
    k_r[0, 2] = (MOTO_CX + MOTO_DOFFS) / w
    c2w_r = torch.eye(4)
    c2w_r[0, 3] = MOTO_BASELINE  # the right camera sits +B along x (u_right = u_left - d)
    imgs = torch.from_numpy(np.stack([left, right])).permute(0, 3, 1, 2)
    small, _ = rescale_and_crop(imgs, k_l[None].repeat(2, 1, 1), (size, size),
                                move_principal_point=True)
    ks = torch.stack([cropped_intrinsics(k[None], (h, w), (size, size), True)[0]
                      for k in (k_l, k_r)])
    extr = torch.stack([torch.eye(4), c2w_r])
    # ground truth at each output pixel's centre: its source pixel (nearest) in the original
    gt_full = MOTO_F * MOTO_BASELINE / (disp + MOTO_DOFFS)
    h_s, w_s = covering_size((h, w), (size, size))
    row, col = (h_s - size) // 2, (w_s - size) // 2
    ys = np.clip(((np.arange(size) + 0.5 + row) * h / h_s).astype(int), 0, h - 1)
    xs = np.clip(((np.arange(size) + 0.5 + col) * w / w_s).astype(int), 0, w - 1)
    gt = gt_full[np.ix_(ys, xs)]
    valid = np.isfinite(gt) & (gt > 0)  # NaN: no ground truth; inf disparity: none either

    def absrel(depth: np.ndarray) -> float:
        return float(np.mean(np.abs(depth[valid] - gt[valid]) / gt[valid]))

    out = []
    images = small.float() / 255.0
    a = images.permute(0, 2, 3, 1).numpy().astype(np.float64)
    depths = 1.0 / np.linspace(1 / MOTO_RANGE[0], 1 / MOTO_RANGE[1], 128)
    sweep = plane_sweep(a[0], a[1], ks[0].double().numpy(), ks[1].double().numpy(),
                        np.eye(4), c2w_r.double().numpy(), depths, window=7)
    out.append({"size": size, "predictor": "plane sweep (7x7 SAD)",
                "absrel": round(absrel(sweep.depth), 4)})
    out.append({"size": size, "predictor": "constant (ground-truth median)",
                "absrel": round(absrel(np.full_like(gt, np.nanmedian(gt))), 4)})
    for name, model in models.items():
        pred = model.predict(images, intrinsics=ks, extrinsics=extr, target_intrinsics=ks[:1],
                             target_extrinsics=extr[:1], near=MOTO_RANGE[0],
                             far=MOTO_RANGE[1])
        out.append({"size": size, "predictor": name,
                    "absrel": round(absrel(pred.depth[0].numpy()), 4)})
    return out


def summarise(rows: list[dict]) -> dict:
    out: dict = {}
    keys = sorted({(r["capture"], r["size"], r["placement"]) for r in rows})
    for capture, size, placement in keys:
        sel = [r for r in rows if (r["capture"], r["size"], r["placement"]) ==
               (capture, size, placement)]
        copy = {(r["pair"], r["target"]): r["psnr"] for r in sel if r["predictor"] == "copy"}
        entry = {"targets": len(copy), "pairs": len({p for p, _ in copy}),
                 "copy": round(float(np.mean(list(copy.values()))), 3)}
        for name in sorted({r["predictor"] for r in sel} - {"copy"}):
            diffs = [r["psnr"] - copy[(r["pair"], r["target"])] for r in sel
                     if r["predictor"] == name]
            d = np.asarray(diffs)
            half = 1.96 * d.std(ddof=1) / math.sqrt(len(d)) if len(d) > 1 else float("nan")
            entry[name] = {"psnr": round(float(np.mean([r["psnr"] for r in sel
                                                          if r["predictor"] == name])), 3),
                           "over_copy": round(float(d.mean()), 3),
                           "over_copy_ci95": [round(float(d.mean() - half), 3),
                                              round(float(d.mean() + half), 3)],
                           "targets_won": int((d > 0).sum())}
        out[f"{capture} {size}x{size} {placement}"] = entry
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True)
    p.add_argument("--realdata", default=str(Path(__file__).resolve().parents[3] / "shared"
                                             / "realdata"))
    p.add_argument("--pose-root", default="outputs/pose")
    p.add_argument("--captures", nargs="+", default=["monstree", "sacre_coeur"])
    p.add_argument("--models", nargs="+", required=True,
                   help="SIZE:NAME[,NAME...] (a shipped name, or LABEL=FILE for a checkpoint "
                   "file)")
    p.add_argument("--gaps", nargs="+", type=int, default=list(GAPS),
                   help="the pairs' gaps in photos (the registered reading: 2 4)")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    by_size = {}
    for spec in args.models:
        size, names = spec.split(":")
        by_size[int(size)] = {n.split("=")[0]: load_model(n.split("=")[-1])
                              for n in names.split(",")}
    posed, rows, depth_rows, started = {}, [], [], time.time()
    for capture in args.captures:
        try:
            posed[capture] = pose_capture(Path(args.realdata) / capture / "images",
                                          Path(args.pose_root) / capture)
        except ValueError as e:  # reported, not hidden
            print(f"{capture}: not posed: {e}", flush=True)
    for size, models in by_size.items():
        for capture, result in posed.items():
            got, sheet, near, far = capture_rows(capture, result, size, models,
                                                 gaps=tuple(args.gaps))
            rows += got
            save_sheet(sheet, ["context i", "context j", "target", "copy", "plane sweep",
                               *models],
                       out / f"sheet_{capture}_{size}.png")
            print(f"{capture} {size}x{size}: {len(got)} rows, near/far {near:.3g}/{far:.3g}, "
                  f"{time.time() - started:.0f} s", flush=True)
        depth_rows += motorcycle_depth(size, models)
    for name, table in (("rows.csv", rows), ("depth.csv", depth_rows)):
        with open(out / name, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(table[0]))
            writer.writeheader()
            writer.writerows(table)
    summary = {"date": time.strftime("%Y-%m-%d"), "machine": platform.processor() or
               platform.machine(), "command": " ".join(os.sys.argv),
               "posed": {c: r.line() for c, r in posed.items()},
               "photos": summarise(rows), "depth": depth_rows}
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary["photos"], indent=1))
    for r in depth_rows:
        print(f"motorcycle {r['size']}x{r['size']} {r['predictor']}: AbsRel {r['absrel']}")


if __name__ == "__main__":
    main()
