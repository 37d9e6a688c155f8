"""Does pruning pay? Rendering time per target view with and without per-target pruning, per
image size, net of the pruning's own cost (a script, not a test: timings are never asserted).

Gaussians come from a trained model on held-out synthetic scenes (default: the shipped tiny
(a) on the standard split of a ``usplat synth`` set), so they have the near-duplicates that
two context views predict for one surface. For sizes above the data's, the context images are
upsampled bilinearly before the model runs (the intrinsics are normalised, so the cameras are
unchanged): the model then predicts one Gaussian per pixel of the larger images, as it would
on data of that size. For each scene the model runs once (not timed); then, interleaved
scene by scene, every pruning setting prunes and renders the scene's targets:

- ``none``: the rasteriser alone (it already skips what culling drops, inside its binning);
- ``cull``: exact culling in torch, then the rasteriser;
- ``cull+merge1px``: culling and merging near-duplicates within a target pixel (the previous
  inference default);
- ``merge1px``: merging without culling first.

ms/view: (prune + render) wall time / targets, median over scenes after a warm-up scene; CPU
ms: process CPU time, same; dPSNR: mean PSNR change of the render against ``none``'s (the
rasteriser's image, not ground truth: what pruning changes); kept: mean fraction of Gaussians
rendered. Net saving = none's ms/view - the setting's. Prints a Markdown table and writes
``--out`` (JSON).

    python train/bench/prune.py --data outputs/demo/data --sizes 64 128 256 --threads 1
"""

import argparse
import platform
import statistics
import time
from pathlib import Path

import usplat_dr  # noqa: F401  (libLLVM before drjit)

ROOT = Path(__file__).resolve().parents[2]


def settings_grid():
    """``usplat bench``'s named settings (``render.prune.PRUNES``), and merging without culling."""
    from usplat_dr.render.prune import PRUNES, PruneSettings

    return {"none": PRUNES["all"], "cull": PRUNES["cull"],
            "cull+merge1px": PRUNES["cull+merge1px"],
            "merge1px": PruneSettings(cull=False, merge=True)}


def scenes(data: str, split: str, count: int):
    """The first ``count`` examples of ``split`` of a ``usplat synth`` set, collated."""
    from torch.utils.data import default_collate

    from usplat_dr.data.dataset import dataset_from_section
    from usplat_dr.evaluation import synthetic_indices

    index = synthetic_indices(data, [split])[split]
    ds = dataset_from_section({"name": "synth", "roots": [data], "evaluation_index": index},
                              "test")
    out = []
    for example in ds:
        out.append(default_collate([example]))
        if len(out) == count:
            break
    if not out:
        raise SystemExit(f"--data {data}: no scenes in split {split!r}")
    return out


def psnr(a, b) -> float:
    """PSNR of two [N, 3, H, W] batches pooled as one image (inf where they are identical)."""
    from usplat_dr.evaluation.metrics import psnr as image_psnr

    def pooled(x):  # [3, N H, W]
        return x.transpose(0, 1).flatten(1, 2)

    return image_psnr(pooled(a), pooled(b)).item()


def measure(model, batches, size: int, grid: dict) -> dict:
    """Per setting, one row per scene: wall ms / view, CPU ms / view, kept fraction, PSNR
    against the unpruned render, pruning ms / view, rasteriser ms / view."""
    import torch
    import torch.nn.functional as F

    from usplat_dr.data.types import model_inputs
    from usplat_dr.render import RasterSettings, rasterize
    from usplat_dr.render.prune import prune as prune_gaussians

    rows = {name: [] for name in grid}
    for i, batch in enumerate(batches):
        inputs = model_inputs(batch, "cpu")
        images = inputs.images
        if images.shape[-1] != size:
            b, v = images.shape[:2]
            inputs = inputs.replaced(images=F.interpolate(
                images.flatten(0, 1), size=(size, size), mode="bilinear", align_corners=False,
                antialias=False).unflatten(0, (b, v)))
        with torch.inference_mode():
            out = model(*inputs, render=False)
        te, ti, tn, tf = (inputs.target_extrinsics, inputs.target_intrinsics, inputs.target_near,
                          inputs.target_far)
        colors = {}
        g = out.gaussians
        b, n = tn.shape
        ext, intr, near = te.flatten(0, 1), ti.flatten(0, 1), tn.flatten()
        bg = torch.zeros(b * n, 3)
        settings = RasterSettings(sh_basis="mvsplat")  # the model's SH basis (decoder.py)
        # the order rotates from scene to scene: the first render after the model runs on
        # colder caches
        names = list(grid)
        # Own timing, not usplat_dr.evaluation.timing: pruning and rendering timed apart in a call.
        for name in names[i % len(names):] + names[:i % len(names)]:
            prune = grid[name]
            w0, c0 = time.perf_counter(), time.process_time()
            with torch.inference_mode():
                gauss = (g.means, g.covariances, g.harmonics, g.opacities)
                kept = 1.0
                if prune is not None:
                    pr = prune_gaussians(ext, intr, near, (size, size), *gauss, prune)
                    gauss = (pr.means, pr.covariances, pr.harmonics, pr.opacities)
                    kept = pr.counts.float().mean().item() / g.means.shape[1]
                w1 = time.perf_counter()
                color = rasterize(ext, intr, near, tf.flatten(), (size, size), bg, *gauss,
                                  settings).color
            w2, c2 = time.perf_counter(), time.process_time()
            colors[name] = color
            rows[name].append([(w2 - w0) * 1e3 / n, (c2 - c0) * 1e3 / n, kept, None,
                               (w1 - w0) * 1e3 / n, (w2 - w1) * 1e3 / n])
        for name in grid:  # against the unpruned render, once all are done
            rows[name][-1][3] = (psnr(colors[name], colors["none"]) if name != "none"
                                 else float("inf"))
    return rows


def fmt_db(d) -> str:
    if d is None:
        return "-"
    return "identical" if d == float("inf") else f"{d:.1f} dB"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default=str(ROOT / "checkpoints" / "tiny_baseline.pt"))
    p.add_argument("--data", required=True, help="a usplat synth set (held-out)")
    p.add_argument("--split", default="standard")
    p.add_argument("--scenes", type=int, default=9, help="scenes per size (the first warms up)")
    p.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    p.add_argument("--threads", type=int, default=None,
                   help="torch and Dr.Jit threads (default: theirs)")
    p.add_argument("--out", default="outputs/bench_prune.json")
    args = p.parse_args()
    if args.scenes < 2:
        p.error("--scenes must be >= 2 (the first scene only warms up)")

    import drjit as dr
    import torch

    from usplat_dr.training.checkpoints import load_model

    if args.threads:
        torch.set_num_threads(args.threads)
        dr.set_thread_count(args.threads)
    model, _ = load_model(args.checkpoint)
    model.eval()
    batches = scenes(args.data, args.split, args.scenes)
    grid = settings_grid()
    results = {}
    lines = [("| size | Gaussians/view | pruning | ms/view | CPU ms/view | pruning ms | "
              "rasteriser ms | rasteriser saves ms | net saving ms/view | kept | dPSNR vs none |"),
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for size in args.sizes:
        rows = measure(model, batches, size, grid)
        stats = {}
        for name, r in rows.items():
            steady = r[1:]  # the first scene compiles kernels for this size
            stats[name] = {
                "ms_per_view": statistics.median(x[0] for x in steady),
                "cpu_ms_per_view": statistics.median(x[1] for x in steady),
                "kept": statistics.mean(x[2] for x in steady),
                "prune_ms_per_view": statistics.median(x[4] for x in steady),
                "render_ms_per_view": statistics.median(x[5] for x in steady),
                "dpsnr_vs_none": (None if name == "none" else
                                  statistics.mean(x[3] for x in steady))}
        base = stats["none"]["ms_per_view"]
        base_render = stats["none"]["render_ms_per_view"]
        gauss = 2 * size * size
        for name, s in stats.items():
            s["net_saving_ms"] = base - s["ms_per_view"]
            d = s["dpsnr_vs_none"]
            lines.append(f"| {size} | {gauss:,} | {name} | {s['ms_per_view']:.1f} | "
                         f"{s['cpu_ms_per_view']:.1f} | {s['prune_ms_per_view']:.1f} | "
                         f"{s['render_ms_per_view']:.1f} | "
                         f"{base_render - s['render_ms_per_view']:+.1f} | "
                         f"{s['net_saving_ms']:+.1f} | "
                         f"{s['kept']:.2f} | {fmt_db(d)} |")
        results[size] = stats
        print(f"size {size}: done", flush=True)
    text = "\n".join(lines)
    print(text)
    meta = {"command": "python train/bench/prune.py " + " ".join(
        f"--{k.replace('_', '-')} {' '.join(map(str, v)) if isinstance(v, list) else v}"
        for k, v in vars(args).items() if v is not None),
            "machine": platform.processor() or platform.machine(),
            "threads": torch.get_num_threads(), "date": time.strftime("%Y-%m-%d"),
            "results": results, "table": text}
    from usplat_dr.io import write_json

    write_json(Path(args.out), meta)


if __name__ == "__main__":
    main()
