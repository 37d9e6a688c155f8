"""The 128x128 (a) against the 64x64 one, by the test registered for it (train/studies/LOG.md,
"Four times the pixels"): on a held-out set rendered at 128x128, per scene of the standard
split (``--split`` names another), PSNR and SSIM of the 128x128 model's renders at 128x128
against those of the 64x64 model (its inputs resized to 64x64 by the data loader, as any
evaluation at 64x64) upsampled 2x by bicubic interpolation; AbsRel of each at its own size;
and both models at 64x64 (what resizing costs). Paired differences with 95% t intervals over
scenes.

    python train/studies/res128_eval.py --model128 step_0002000.ckpt \\
        --model64 tiny_baseline --data outputs/big128/test5000 --out outputs/res128_eval

``--rendered-up`` adds the small model's Gaussians rendered at the large size (the rasteriser
draws any size; no upsampling of pixels), also as a fourth column of ``comparison.png``.
``--size 256`` makes the same comparison one octave up (a 256x256 model against a 128x128 one
upsampled; the columns are then named ``psnr_256``, ``psnr_128_up``, ...), ``--device cuda``
runs both models on a GPU (scripts/run.sh gpu-train).

Writes ``OUT/per_scene.csv``, ``OUT/summary.json`` and ``OUT/comparison.png`` (ground truth,
the large model, the small model upsampled, for the first scenes).
"""

import argparse
import csv
import re
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import default_collate

import usplat_dr  # noqa: F401  (libLLVM first)
from usplat_dr.data.dataset import dataset_from_section
from usplat_dr.data.types import model_inputs
from usplat_dr.evaluation import depth_metrics, held_out_scenes, nan_mean
from usplat_dr.evaluation.metrics import psnr, ssim
from usplat_dr.evaluation.verdict import t_interval
from usplat_dr.io import atomic_open, write_json
from usplat_dr.training.loader import load

#: The registered success test: PSNR at least this much above the upsampled 64x64 renders
#: (and SSIM above theirs).
MARGIN_DB = 1.0


def upsample(images: torch.Tensor, factor: int) -> torch.Tensor:
    """[..., 3, H, W] in [0, 1] -> bicubic ``factor`` x upsampling, clamped to [0, 1] (bicubic
    overshoots at edges)."""
    shape = images.shape
    flat = images.reshape(-1, *shape[-3:])
    up = F.interpolate(flat, scale_factor=factor, mode="bicubic", align_corners=False)
    return up.clamp(0, 1).reshape(*shape[:-2], *up.shape[-2:])


def examples(dataset: dict, index: str):
    """The split's examples as batches of 1, read once in the index's order."""
    for example in dataset_from_section({**dataset, "evaluation_index": index}, "test"):
        yield default_collate([example])


def render(model, batch, device: str = "cpu") -> tuple[torch.Tensor, float]:
    """One scene's target renders [T, 3, H, W] (on the CPU) and mean AbsRel over its targets."""
    with torch.no_grad():
        result = model(*model_inputs(batch, device))
    depth, alpha = result.depth.cpu(), result.alpha.cpu()
    gt_depth = batch["target"].get("depth")
    rel = float("nan")
    if gt_depth is not None:
        rel = nan_mean([depth_metrics(depth[0, j], alpha[0, j], gt_depth[0, j])["abs_rel"]
                        for j in range(depth.shape[1])])
    return result.color[0].clamp(0, 1).cpu(), rel


def render_at(model, batch, shape: tuple[int, int], device: str = "cpu") -> torch.Tensor:
    """One scene's target renders [T, 3, *shape] of the Gaussians ``model`` predicts from
    ``batch`` (at its own size), rendered at ``shape`` (the intrinsics are normalised)."""
    inputs = model_inputs(batch, device)
    with torch.no_grad():
        out = model(*inputs, render=False)
        model.render_targets(out, inputs.targets, shape)
    return out.color[0].clamp(0, 1).cpu()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model128", "--model-large", dest="model128", required=True,
                   help="the model of --size (checkpoint or name)")
    p.add_argument("--model64", "--model-small", dest="model64", default="tiny_baseline",
                   help="the model of half --size")
    p.add_argument("--size", type=int, default=128,
                   help="the large model's image size (the small one's is half)")
    p.add_argument("--device", default="cpu", help="cpu, or cuda for a GPU")
    p.add_argument("--data", required=True, help="a usplat synth test root at --size")
    p.add_argument("--scenes", type=int, default=None, help="the first N scenes (default all)")
    p.add_argument("--split", default="standard",
                   help="the evaluation split of --data (standard, extrapolation, ...)")
    p.add_argument("--threads", type=int, default=1, help="torch threads")
    p.add_argument("--images", type=int, default=4, help="scenes shown in comparison.png")
    p.add_argument("--rendered-up", action="store_true",
                   help="also score the small model's Gaussians rendered at the large size "
                   "(columns psnr_64_rendered_up, ssim_64_rendered_up; compared in the summary's "
                   "rendered_up)")
    p.add_argument("--out", required=True, type=Path, help="folder for the results")
    args = p.parse_args(argv)
    if args.size < 8 or args.size % 2:
        p.error(f"--size must be an even number of pixels >= 8, got {args.size}")
    torch.set_num_threads(args.threads)
    hi, lo = args.size, args.size // 2
    big = load(args.model128, device=args.device).eval()
    small = load(args.model64, device=args.device).eval()
    set128, index, scenes = held_out_scenes(args.data, args.split, args.scenes, size=hi)
    set64 = {**set128, "image_shape": [lo, lo]}
    rows, shown = [], []
    # one pass over the chunks at each size (the same scenes, in the same order)
    for k, (b128, b64) in enumerate(zip(examples(set128, index), examples(set64, index))):
        if k == len(scenes):
            break
        scene = b128["scene"][0]
        assert b64["scene"][0] == scene and scene == scenes[k], (scene, scenes[k])
        gt128, gt64 = b128["target"]["image"][0], b64["target"]["image"][0]
        pred128, rel128 = render(big, b128, args.device)
        pred64, rel64 = render(small, b64, args.device)
        up = upsample(pred64, 2)
        big_at64, rel_big64 = render(big, b64, args.device)
        rows.append({
            "scene": scene,
            "psnr_128": psnr(pred128, gt128).mean().item(),
            "psnr_64_up": psnr(up, gt128).mean().item(),
            "ssim_128": ssim(pred128, gt128).mean().item(),
            "ssim_64_up": ssim(up, gt128).mean().item(),
            "abs_rel_128": rel128, "abs_rel_64": rel64,
            "psnr_128_at64": psnr(big_at64, gt64).mean().item(),
            "psnr_64_at64": psnr(pred64, gt64).mean().item(),
            "ssim_128_at64": ssim(big_at64, gt64).mean().item(),
            "ssim_64_at64": ssim(pred64, gt64).mean().item(),
            "abs_rel_128_at64": rel_big64})
        if args.rendered_up:
            drawn = render_at(small, b64, (hi, hi), args.device)
            rows[-1].update({"psnr_64_rendered_up": psnr(drawn, gt128).mean().item(),
                             "ssim_64_rendered_up": ssim(drawn, gt128).mean().item()})
        if k < args.images:
            row = [gt128[0], pred128[0], up[0]] + ([drawn[0]] if args.rendered_up else [])
            shown.append(torch.cat(row, dim=-1))
        print(f"{k + 1}/{len(scenes)} {scene}: {hi} {rows[-1]['psnr_128']:.2f} dB, "
              f"{lo} upsampled {rows[-1]['psnr_64_up']:.2f} dB", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    with atomic_open(args.out / "per_scene.csv", "w") as f:
        w = csv.DictWriter(f, fieldnames=list(_named(rows[0], hi)))
        w.writeheader()
        w.writerows(_named(r, hi) for r in rows)
    col = {key: np.array([r[key] for r in rows]) for key in rows[0] if key != "scene"}

    def paired(a: str, b: str) -> dict:
        d = col[a] - col[b]
        low, high = t_interval(d)
        return {"mean": float(np.nanmean(d)), "low": low, "high": high}

    summary = {
        "scenes": len(rows), "data": str(args.data), "split": args.split,
        "model128": args.model128,
        "model64": args.model64,
        "means": {key: float(np.nanmean(v)) for key, v in col.items()},
        "at128": {"psnr": paired("psnr_128", "psnr_64_up"),
                  "ssim": paired("ssim_128", "ssim_64_up"),
                  "abs_rel": paired("abs_rel_128", "abs_rel_64")},
        "at64": {"psnr": paired("psnr_128_at64", "psnr_64_at64"),
                 "ssim": paired("ssim_128_at64", "ssim_64_at64"),
                 "abs_rel": paired("abs_rel_128_at64", "abs_rel_64")}}
    if args.rendered_up:  # the large model against the small one's Gaussians drawn large
        summary["rendered_up"] = {"psnr": paired("psnr_128", "psnr_64_rendered_up"),
                                  "ssim": paired("ssim_128", "ssim_64_rendered_up"),
                                  "against_upsampled_psnr": paired("psnr_64_rendered_up",
                                                                   "psnr_64_up")}
    gain = summary["at128"]
    summary["success"] = bool(gain["psnr"]["mean"] >= MARGIN_DB and gain["ssim"]["mean"] > 0)
    summary["size"] = hi
    write_json(args.out / "summary.json", _named(summary, hi))
    if shown:
        from PIL import Image
        grid = torch.cat(shown, dim=-2).permute(1, 2, 0).mul(255).round().byte().numpy()
        # columns: GT | large | small upsampled (| small's Gaussians drawn large)
        Image.fromarray(grid).save(args.out / "comparison.png")
    m = summary["means"]
    print(f"at {hi}x{hi} over {len(rows)} scenes: {hi} model {m['psnr_128']:.3f} dB / SSIM "
          f"{m['ssim_128']:.4f} / AbsRel {m['abs_rel_128']:.4f}; {lo} model upsampled "
          f"{m['psnr_64_up']:.3f} dB / {m['ssim_64_up']:.4f} (its AbsRel at {lo}: "
          f"{m['abs_rel_64']:.4f})")
    for where, size in (("at128", hi), ("at64", lo)):
        s = summary[where]
        print(f"at {size}: PSNR {s['psnr']['mean']:+.3f} [{s['psnr']['low']:+.3f}, "
              f"{s['psnr']['high']:+.3f}] dB, SSIM {s['ssim']['mean']:+.4f} "
              f"[{s['ssim']['low']:+.4f}, {s['ssim']['high']:+.4f}], AbsRel "
              f"{s['abs_rel']['mean']:+.4f} [{s['abs_rel']['low']:+.4f}, "
              f"{s['abs_rel']['high']:+.4f}]")
    if args.rendered_up:
        s, u = summary["rendered_up"]["psnr"], summary["rendered_up"]["against_upsampled_psnr"]
        print(f"the {lo} model's Gaussians rendered at {hi}: {m['psnr_64_rendered_up']:.3f} dB "
              f"({u['mean']:+.3f} [{u['low']:+.3f}, {u['high']:+.3f}] against its renders "
              f"upsampled); the {hi} model against them {s['mean']:+.3f} [{s['low']:+.3f}, "
              f"{s['high']:+.3f}] dB")
    print(f"success (>= +{MARGIN_DB} dB and higher SSIM at {hi}x{hi}): {summary['success']}")
    return 0


def _named(obj, size: int):
    """``obj`` (a dict, nested) with the keys' sizes for a comparison at ``size``: the code
    names the large size 128 and the small 64 (the registered test's own names, kept as they
    are at 128); at 256 a key ``psnr_64_up`` becomes ``psnr_128_up``."""
    names = {"128": str(size), "64": str(size // 2)}
    if isinstance(obj, dict):
        return {re.sub(r"128|64", lambda m: names[m.group()], k): _named(v, size)
                for k, v in obj.items()}
    return obj


if __name__ == "__main__":
    sys.exit(main())
