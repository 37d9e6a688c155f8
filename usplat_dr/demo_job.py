"""``usplat demo``: the main job. On a fresh machine, with no arguments: render a synthetic
dataset with Mitsuba, train variant (a) (the primary network) and UniqueSplat (c) with the
same budget, evaluate both on held-out synthetic scenes and their stress splits, and write a
report folder (``report.md`` with PNGs: novel views next to ground truth, depth maps, training
curves, per-split results).

Budgets: ``full`` (about 15 minutes on a 2-core CPU) and ``quick`` (a minute or two, for CI).
"""

import json
import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Budget:
    train_scenes: int
    test_scenes: int
    frames: int
    size: int
    steps: int
    spp: int


BUDGETS = {
    "full": Budget(train_scenes=24, test_scenes=12, frames=24, size=64, steps=700, spp=64),
    "quick": Budget(train_scenes=3, test_scenes=3, frames=12, size=32, steps=12, spp=8),
}
VARIANTS = {"baseline": "(a) primary network", "full": "(c) UniqueSplat"}
def _config() -> Path:
    from usplat_dr.training import CONFIG_DIR

    return CONFIG_DIR / "synthetic_tiny.yaml"


def training_config(data: Path, out: Path, budget: Budget, variant: str) -> dict:
    from usplat_dr.config import load_config

    gap_max = max(4, budget.frames // 3)
    config = _config()
    return load_config([config] if config.is_file() else [], [
        f"dataset.roots=[{data}]", f"dataset.image_shape=[{budget.size},{budget.size}]",
        f"output_dir={out}", f"model.variant={variant}", f"train.steps={budget.steps}",
        f"train.checkpoint_every={max(budget.steps // 4, 1)}",
        f"train.validate_every={budget.steps}", "train.log_every=5", "loss.lpips=0.0",
        "optimizer.lr=1e-3",
        "dataset.view_sampler.min_distance_between_context_views=3",
        "dataset.view_sampler.initial_min_distance_between_context_views=3",
        f"dataset.view_sampler.max_distance_between_context_views={gap_max}",
        f"dataset.view_sampler.initial_max_distance_between_context_views={gap_max}"])


def _curves(runs: dict, path: Path) -> Path:
    import csv

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
    for variant, run in runs.items():
        with open(run / "metrics.csv") as f:
            rows = list(csv.DictReader(f))
        steps = [int(r["step"]) for r in rows]
        for ax, key in ((axes[0], "loss"), (axes[1], "psnr")):
            values = [float(r[key]) for r in rows]
            line, = ax.plot(steps, values, alpha=0.25, linewidth=0.8)
            w = max(1, len(values) // 15)  # moving average over ~1/15 of the run
            smooth = [sum(values[max(0, i - w + 1):i + 1]) / len(values[max(0, i - w + 1):i + 1])
                      for i in range(len(values))]
            ax.plot(steps, smooth, color=line.get_color(), label=VARIANTS[variant])
    axes[0].set(xlabel="step", ylabel="training loss (MSE)", yscale="log")
    axes[1].set(xlabel="step", ylabel="training PSNR (dB)")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    from usplat_dr.io import atomic_open

    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=110)
    plt.close(fig)
    return path


def run_demo(out: str | Path = "outputs/demo", budget: str = "full", seed: int = 0,
             jobs: int = 0) -> Path:
    """Run the whole job; returns the path of ``report.md``."""
    import torch

    from usplat_dr.data.synth import synthesize
    from usplat_dr.evaluation import evaluate, load_model, synthetic_indices
    from usplat_dr.training import train

    if budget not in BUDGETS:
        raise ValueError(f"budget must be one of {sorted(BUDGETS)}, got {budget!r}")
    b = BUDGETS[budget]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    timings = {}

    data = out / "data"
    stamp = data / "demo.json"
    spec = {"budget": budget, "seed": seed, **b.__dict__}
    if not (stamp.is_file() and json.loads(stamp.read_text()) == spec):  # reuse a finished set
        shutil.rmtree(data, ignore_errors=True)
        for old in [*out.glob("train_*"), *out.glob("eval_*")]:  # runs on older data
            shutil.rmtree(old, ignore_errors=True)
        t = time.perf_counter()
        cores = jobs or min(2, torch.get_num_threads())
        synthesize(data, scenes=b.train_scenes, frames=b.frames, resolution=(b.size, b.size),
                   seed=seed, spp=b.spp, stage="train", previews=0, jobs=cores)
        synthesize(data, scenes=b.test_scenes, frames=b.frames, resolution=(b.size, b.size),
                   seed=seed + 1000, spp=b.spp, stage="test", previews=4, jobs=cores)
        stamp.write_text(json.dumps(spec))
        timings["synthetic data"] = time.perf_counter() - t

    runs, summaries = {}, {}
    for variant in VARIANTS:
        run = out / f"train_{variant}"
        t = time.perf_counter()
        train(training_config(data, run, b, variant), resume=True)
        timings[f"training {variant}"] = time.perf_counter() - t
        runs[variant] = run
        model, _ = load_model(run / "checkpoints" / "last.ckpt")
        t = time.perf_counter()
        summaries[variant] = evaluate(
            model, {"name": "synth", "roots": [str(data)], "image_shape": [b.size, b.size]},
            synthetic_indices(data), out / f"eval_{variant}", label=variant)
        timings[f"evaluation {variant}"] = time.perf_counter() - t
    _curves(runs, out / "training_curves.png")
    timings["total"] = time.perf_counter() - t_start
    report = write_report(out, b, budget, summaries, timings)
    print(f"report: {report}")
    return report


def write_report(out: Path, b: Budget, budget: str, summaries: dict, timings: dict) -> Path:
    from usplat_dr.io import atomic_open

    lines = [
        "# usplat-dr demo report", "",
        f"Budget `{budget}`: {b.train_scenes} training and {b.test_scenes} test scenes "
        f"rendered by Mitsuba ({b.frames} frames, {b.size}x{b.size}), the `tiny` preset "
        f"trained for {b.steps} steps per variant (same data, seed, schedule), evaluated on "
        f"the held-out scenes with the field's protocol.", "",
        "## Efficiency and accuracy (standard split)", "",
        "| variant | parameters | time per scene | peak memory | PSNR | SSIM | depth AbsRel |",
        "|---|---|---|---|---|---|---|"]
    for variant, s in summaries.items():
        std = s["splits"].get("standard", next(iter(s["splits"].values())))
        lines.append(f"| {VARIANTS[variant]} | {s['parameters'] / 1e6:.2f}M | "
                     f"{1000 * s['time_per_scene_s']:.0f} ms | {s['peak_memory_gib']:.2f} GiB "
                     f"| {std['psnr']:.2f} | {std['ssim']:.3f} | {std['abs_rel']:.3f} |")
    lines += ["", "Time per scene: 2 context views in, Gaussians and renders for every target "
              "of the evaluation index (CPU, 2 threads); peak memory: the process's peak "
              "RSS. LPIPS: unavailable (no VGG/LPIPS weight files in the demo).", "",
              "## Per split (PSNR / SSIM / depth AbsRel)", "",
              "| split | scenes | " + " | ".join(VARIANTS[v] for v in summaries) + " |",
              "|---|---|" + "---|" * len(summaries)]
    first = next(iter(summaries.values()))
    for split, m in first["splits"].items():
        cells = [f"{s['splits'][split]['psnr']:.2f} / {s['splits'][split]['ssim']:.3f} / "
                 f"{s['splits'][split]['abs_rel']:.3f}" for s in summaries.values()]
        lines.append(f"| {split} | {m['scenes']} | " + " | ".join(cells) + " |")
    lines += ["", "## Training", "", "![training curves](training_curves.png)", "",
              "## Novel views", "",
              "Each row: context views, ground truth, prediction, predicted depth."]
    for variant in summaries:
        renders = sorted((out / f"eval_{variant}" / "renders" / "standard").glob("*.png"))[:2]
        for r in renders:
            lines.append(f"\n{VARIANTS[variant]}, {r.stem}:\n\n![{r.stem}]"
                         f"({r.relative_to(out)})")
    lines += ["", "## Wall time", "", "| stage | seconds |", "|---|---|"]
    lines += [f"| {k} | {v:.0f} |" for k, v in timings.items()]
    path = out / "report.md"
    with atomic_open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
    return path
