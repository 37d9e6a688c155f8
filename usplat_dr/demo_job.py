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

import numpy as np

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
#: The demo's size preset: the smallest within 0.3 dB of the best in `usplat bench`
#: (BENCHMARKS.md, "Speed against accuracy").
PRESET = "tiny"
def _config() -> Path:
    from usplat_dr.training import CONFIG_DIR

    return CONFIG_DIR / "synthetic_tiny.yaml"


def training_config(data: Path, out: Path, budget: Budget, variant: str,
                    preset: str = "tiny") -> dict:
    from usplat_dr.config import load_config

    gap_max = max(4, budget.frames // 3)
    config = _config()
    return load_config([config] if config.is_file() else [], [
        f"dataset.roots=[{data}]", f"dataset.image_shape=[{budget.size},{budget.size}]",
        f"output_dir={out}", f"model.variant={variant}", f"model.preset={preset}",
        f"train.steps={budget.steps}",
        f"train.checkpoint_every={max(budget.steps // 4, 1)}",
        f"train.validate_every={budget.steps}", "train.log_every=5", "loss.lpips=0.0",
        "optimizer.lr=1e-3",
        "dataset.view_sampler.min_distance_between_context_views=3",
        "dataset.view_sampler.initial_min_distance_between_context_views=3",
        f"dataset.view_sampler.max_distance_between_context_views={gap_max}",
        f"dataset.view_sampler.initial_max_distance_between_context_views={gap_max}"])


def _read_metrics(run: Path) -> list[dict]:
    import csv

    with open(run / "metrics.csv") as f:
        return list(csv.DictReader(f))


GRAD_LABELS = {"grad_primary": "primary network", "grad_agnostic": "view-agnostic (e_a, H_a)",
               "grad_specific": "view-specific H_s",
               "grad_view_features": "view-specific features (ResNet, Proj, phi)"}


def _curves(runs: dict, path: Path) -> Path:
    """Training loss, PSNR and the gradient norms of the network's parts (before clipping)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 3.4))
    for variant, run in runs.items():
        rows = _read_metrics(run)
        steps = [int(r["step"]) for r in rows]
        for ax, key in ((axes[0], "loss"), (axes[1], "psnr")):
            values = [float(r[key]) for r in rows]
            line, = ax.plot(steps, values, alpha=0.25, linewidth=0.8)
            ax.plot(steps, _smooth(values), color=line.get_color(),
                    label=VARIANTS.get(variant, variant))
        for key, label in GRAD_LABELS.items():
            values = [float(r[key]) for r in rows if r.get(key)]
            if values:
                axes[2].plot(steps[-len(values):], _smooth(values), linewidth=1,
                             label=f"{VARIANTS.get(variant, variant)[:3]} {label}")
    axes[0].set(xlabel="step", ylabel="training loss (MSE)", yscale="log")
    axes[1].set(xlabel="step", ylabel="training PSNR (dB)")
    axes[2].set(xlabel="step", ylabel="gradient norm before clipping", yscale="log")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    from usplat_dr.io import atomic_open

    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=110)
    plt.close(fig)
    return path


def _smooth(values: list[float]) -> list[float]:
    """Moving average over ~1/15 of the run."""
    w = max(1, len(values) // 15)
    return [sum(values[max(0, i - w + 1):i + 1]) / len(values[max(0, i - w + 1):i + 1])
            for i in range(len(values))]


def stability(run: Path) -> dict:
    """Loss and gradient-norm statistics of a training run's ``metrics.csv``: per part the
    median and maximum gradient norm (before clipping) and the last quarter's median against
    the first quarter's (bounded: the ratio stays near or below 1), and the skipped steps."""
    rows = _read_metrics(run)
    q = max(1, len(rows) // 4)
    loss = [float(r["loss"]) for r in rows]
    out = {"steps": int(rows[-1]["step"]), "skipped": int(rows[-1]["skipped"]),
           "loss_first_quarter": float(np.median(loss[:q])),
           "loss_last_quarter": float(np.median(loss[-q:])), "parts": {}}
    for key in ("grad_norm", *GRAD_LABELS):
        values = [float(r[key]) for r in rows if r.get(key)]
        if values:
            out["parts"][key] = {"median": float(np.median(values)), "max": max(values),
                                 "last_over_first_quarter": float(
                                     np.median(values[-q:]) / np.median(values[:q]))}
    return out


def ensure_data(out: Path, budget: str, seed: int = 0, jobs: int = 0) -> bool:
    """The demo's synthetic train and test sets in ``out/data`` (kept when they match
    ``budget`` and ``seed``; else remade, and runs trained on older data removed). Returns
    whether it rendered them."""
    import torch

    from usplat_dr.data.synth import synthesize

    b = BUDGETS[budget]
    data = out / "data"
    stamp = data / "demo.json"
    spec = {"budget": budget, "seed": seed, **b.__dict__}
    if stamp.is_file() and json.loads(stamp.read_text()) == spec:
        return False
    shutil.rmtree(data, ignore_errors=True)
    for old in [*out.glob("train_*"), *out.glob("eval_*"), out / "bench"]:
        shutil.rmtree(old, ignore_errors=True)
    cores = jobs or min(2, torch.get_num_threads())
    synthesize(data, scenes=b.train_scenes, frames=b.frames, resolution=(b.size, b.size),
               seed=seed, spp=b.spp, stage="train", previews=0, jobs=cores)
    synthesize(data, scenes=b.test_scenes, frames=b.frames, resolution=(b.size, b.size),
               seed=seed + 1000, spp=b.spp, stage="test", previews=4, jobs=cores)
    stamp.write_text(json.dumps(spec))
    return True


def run_demo(out: str | Path = "outputs/demo", budget: str = "full", seed: int = 0,
             jobs: int = 0) -> Path:
    """Run the whole job; returns the path of ``report.md``."""

    from usplat_dr.evaluation import evaluate, load_model, synthetic_indices
    from usplat_dr.training import train

    if budget not in BUDGETS:
        raise ValueError(f"budget must be one of {sorted(BUDGETS)}, got {budget!r}")
    b = BUDGETS[budget]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    timings = {}

    if ensure_data(out, budget, seed, jobs):
        timings["synthetic data"] = time.perf_counter() - t_start
    data = out / "data"

    runs, summaries = {}, {}
    for variant in VARIANTS:
        run = out / f"train_{variant}"
        t = time.perf_counter()
        train(training_config(data, run, b, variant, PRESET), resume=True)
        timings[f"training {variant}"] = time.perf_counter() - t
        runs[variant] = run
        model, _ = load_model(run / "checkpoints" / "last.ckpt")
        t = time.perf_counter()
        summaries[variant] = evaluate(
            model, {"name": "synth", "roots": [str(data)], "image_shape": [b.size, b.size]},
            synthetic_indices(data), out / f"eval_{variant}", label=variant)
        timings[f"evaluation {variant}"] = time.perf_counter() - t
    _curves(runs, out / "training_curves.png")
    t = time.perf_counter()
    worst = {v: worst_cases(out, b, v) for v in runs}
    timings["worst-case renders"] = time.perf_counter() - t
    t = time.perf_counter()
    from usplat_dr.bench_job import BenchConfig, load_models, measure, write_results

    models = load_models({BenchConfig(PRESET, v): r for v, r in runs.items()}, "cpu")
    bench = write_results(measure(models, data, b.size), b.size, out / "bench_demo")
    timings["speed/accuracy bench"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_start
    report = write_report(out, b, budget, summaries, timings, worst, bench,
                          {v: stability(r) for v, r in runs.items()})
    print(f"report: {report}")
    return report


def _stability_lines(stable: dict) -> list[str]:
    if not stable:
        return []
    lines = ["Gradient norms before clipping (clip at 0.5): median / maximum, and the last "
             "quarter's median over the first quarter's; skipped non-finite steps.", "",
             "| variant | part | median | max | last/first quarter |", "|---|---|---|---|---|"]
    for variant, st in stable.items():
        for key, p in st["parts"].items():
            lines.append(f"| {VARIANTS[variant]} | {GRAD_LABELS.get(key, 'all parameters')} "
                         f"| {p['median']:.3g} | {p['max']:.3g} | "
                         f"{p['last_over_first_quarter']:.2f} |")
    lines += ["", "Skipped steps: " + ", ".join(
        f"{VARIANTS[v]} {st['skipped']} of {st['steps']}" for v, st in stable.items()), ""]
    return lines


def worst_cases(out: Path, b: Budget, variant: str) -> dict:
    """Per split, the comparison sheet of the scene with the lowest PSNR (from the
    evaluation's ``per_scene.csv``): ``{split: png path, split + "_psnr": its PSNR}``."""
    import csv

    import torch

    from usplat_dr.evaluation import load_example, load_model, save_comparison, synthetic_indices

    with open(out / f"eval_{variant}" / "per_scene.csv") as f:
        rows = list(csv.DictReader(f))
    model, _ = load_model(out / f"train_{variant}" / "checkpoints" / "last.ckpt")
    indices = synthetic_indices(out / "data")
    dataset = {"name": "synth", "roots": [str(out / "data")], "image_shape": [b.size, b.size]}
    found = {}
    from usplat_dr.training import scene_args

    for split in indices:
        mine = [r for r in rows if r["split"] == split]
        if not mine:
            continue
        worst = min(mine, key=lambda r: float(r["psnr"]))
        batch = load_example(dataset, indices[split], worst["scene"])
        with torch.no_grad():
            result = model(*scene_args(batch, torch.device("cpu")))
        found[split] = save_comparison(
            out / f"eval_{variant}" / "worst" / f"{split}_{worst['scene']}.png", batch, result)
        found[split + "_psnr"] = float(worst["psnr"])
    return found


def write_report(out: Path, b: Budget, budget: str, summaries: dict, timings: dict,
                 worst: dict | None = None, bench: dict | None = None,
                 stable: dict | None = None) -> Path:
    from usplat_dr.io import atomic_open

    lines = [
        "# usplat-dr demo report", "",
        f"Budget `{budget}`: {b.train_scenes} training and {b.test_scenes} test scenes "
        f"rendered by Mitsuba ({b.frames} frames, {b.size}x{b.size}), the `{PRESET}` preset "
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
    if worst:
        lines += ["", "### Worst cases", "",
                  "Per split, the held-out scene with the lowest PSNR (context views, ground "
                  "truth, prediction, depth per target)."]
        for split in first["splits"]:
            for variant in summaries:
                w = worst.get(variant, {})
                if split in w:
                    lines.append(f"\n{VARIANTS[variant]}, {split}: {w[split].stem} "
                                 f"({w[split + '_psnr']:.2f} dB)\n\n![{split}]"
                                 f"({w[split].relative_to(out)})")
    if bench:
        lines += ["", "## Speed against accuracy", "",
                  "The demo's two models, measured by `usplat bench`'s code on the standard "
                  "split: Gaussian budgets (pruning per target before rasterising) at "
                  f"{b.size}x{b.size} and a smaller render size. `usplat bench` adds the "
                  "`small` and `paper` presets and variant (b).", "",
                  "![speed against accuracy](bench_demo/bench.png)", "",
                  (out / "bench_demo" / "bench.md").read_text().rstrip(), "",
                  "Pruning (worst PSNR change over the models, mean fraction of Gaussians "
                  "kept; on by default where it costs less than 0.05 dB):", "",
                  "| pruning | worst PSNR change | kept | safe |", "|---|---|---|---|"]
        for name, p in sorted(bench["pruning"].items()):
            lines.append(f"| {name} | {p['worst_psnr_change_db']:+.3f} dB | "
                         f"{p['kept_fraction']:.2f} | {'yes' if p['safe'] else 'no'} |")
    full_bench = out / "bench" / "bench.md"
    if full_bench.is_file():
        lines += ["", "### Full `usplat bench` (all presets)", "",
                  "![usplat bench](bench/bench.png)", "", full_bench.read_text().rstrip()]
    lines += ["", "## Training", "", "![training curves](training_curves.png)", "",
              *_stability_lines(stable or {}),
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
