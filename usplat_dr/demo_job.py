"""``usplat demo``: the main job. On a fresh machine, with no arguments: render fresh held-out
synthetic scenes with Mitsuba, evaluate the shipped checkpoints (``checkpoints/manifest.json``:
the trained primary network (a), and (a) continued, (b) and (c) fine-tuned from it by the
paper's protocol) with the field's protocol on them and their stress splits, give the verdict
on view conditioning with bootstrap intervals over the scenes, fine-tune (a) and (c) briefly
from the shipped (a) to show that training works, and write a report folder (``report.md``
with PNGs: the verdict chart, novel views next to ground truth, depth maps, training curves,
worst cases, speed against accuracy, and where the numbers came from).

Budgets: ``full`` (about 8 minutes on a 2-core CPU) and ``quick`` (a minute or two, for CI).
The multi-seed verdict (fine-tuning seeds x held-out scenes) is ``train/verdict_study.py``; its
result is in BENCHMARKS.md.
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
    train_scenes: int  # the brief fine-tuning's training set
    test_scenes: int  # fresh held-out scenes (a seed no checkpoint was trained or tested on)
    frames: int
    size: int
    steps: int  # brief fine-tuning steps per variant
    spp: int
    scratch_steps: int  # `usplat bench`'s presets without a shipped checkpoint: from scratch


BUDGETS = {
    "full": Budget(train_scenes=24, test_scenes=48, frames=24, size=64, steps=150, spp=64,
                   scratch_steps=700),
    "quick": Budget(train_scenes=3, test_scenes=3, frames=12, size=32, steps=4, spp=8,
                    scratch_steps=12),
}
VARIANTS = {"baseline": "(a) primary network", "agnostic": "(b) + view-agnostic",
            "full": "(c) UniqueSplat"}
#: The demo's size preset: the smallest within 0.3 dB of the best in `usplat bench`
#: (BENCHMARKS.md, "Speed against accuracy").
PRESET = "tiny"
#: The shipped checkpoints the demo reads (names in checkpoints/manifest.json): the trained
#: primary network, and per variant the model fine-tuned from it for the same steps (for (a):
#: trained on, the control the others are paired with).
BASE = "tiny_baseline"
SHIPPED = {"baseline": "tiny_baseline_continued", "agnostic": "tiny_agnostic",
           "full": "tiny_full"}
#: Where the shipped checkpoints are: package data in a wheel install (usplat_dr/checkpoints,
#: pyproject.toml maps the repository's checkpoints/ there), else the repository's
#: checkpoints/ folder (a source checkout or an editable install).
CHECKPOINTS = next((p for p in (Path(__file__).parent / "checkpoints",
                                Path(__file__).parents[1] / "checkpoints") if p.is_dir()),
                   Path(__file__).parents[1] / "checkpoints")
#: The brief fine-tuning's recipe (the verdict study's, fewer steps).
FINETUNE_LR = 2e-4


def shipped_checkpoints(root: Path = CHECKPOINTS) -> dict[str, Path]:
    """``{manifest name: file}`` of the shipped checkpoints, checked against the manifest."""
    manifest = root / "manifest.json"
    if not manifest.is_file():
        raise FileNotFoundError(f"no {manifest}: the demo starts from the shipped checkpoints "
                                f"(train them with train/ship_checkpoint.py; see README)")
    entries = json.loads(manifest.read_text())
    return {e["name"]: root / e["file"] for e in entries}


#: The packaged config the demo's runs start from (usplat_dr/configs/).
CONFIG = "synthetic_tiny_depth.yaml"


def training_config(data: Path, out: Path, budget: Budget, variant: str,
                    preset: str = "tiny", init: Path | None = None) -> dict:
    """The demo's training run: with ``init`` (a trained (a)) the paper's fine-tuning
    protocol at ``FINETUNE_LR``; without, from scratch (``usplat bench``'s other presets)."""
    from usplat_dr.config import load_config

    gap_max = max(4, budget.frames // 3)
    start = ([f"model.init_from={init}", f"optimizer.lr={FINETUNE_LR}",
              "optimizer.warm_up_fraction=0.05"] if init else ["optimizer.lr=1e-3"])
    steps = budget.steps if init else budget.scratch_steps
    return load_config([CONFIG], [
        f"dataset.roots=[{data}]", f"dataset.image_shape=[{budget.size},{budget.size}]",
        f"output_dir={out}", f"model.variant={variant}", f"model.preset={preset}",
        f"train.steps={steps}", f"train.checkpoint_every={max(steps // 4, 1)}",
        f"train.validate_every={steps}", "train.log_every=5", *start,
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
             jobs: int = 0, checkpoints: Path = CHECKPOINTS) -> Path:
    """Run the whole job; returns the path of ``report.md``."""
    from usplat_dr.bench_job import BenchConfig, measure, write_results
    from usplat_dr.evaluation import evaluate, load_model, synthetic_indices
    from usplat_dr.provenance import provenance
    from usplat_dr.training import train
    from usplat_dr.verdict import chart, compare

    if budget not in BUDGETS:
        raise ValueError(f"budget must be one of {sorted(BUDGETS)}, got {budget!r}")
    b = BUDGETS[budget]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    shipped = shipped_checkpoints(checkpoints)
    missing = sorted({BASE, *SHIPPED.values()} - set(shipped))
    if missing:
        raise FileNotFoundError(f"the manifest in {checkpoints} lacks {missing}")
    t_start = time.perf_counter()
    timings = {}
    if ensure_data(out, budget, seed, jobs):
        timings["synthetic data"] = time.perf_counter() - t_start
    data = out / "data"
    dataset = {"name": "synth", "roots": [str(data)], "image_shape": [b.size, b.size]}
    indices = synthetic_indices(data)

    # ---- the shipped checkpoints on fresh held-out scenes ----
    summaries = {}
    models = {"base": shipped[BASE], **{v: shipped[n] for v, n in SHIPPED.items()}}
    for variant, path in models.items():
        t = time.perf_counter()
        model, _ = load_model(path)
        summaries[variant] = evaluate(model, dataset, indices, out / f"eval_shipped_{variant}",
                                      label=variant)
        timings[f"evaluation shipped {variant}"] = time.perf_counter() - t
    verdict = compare({v: [out / f"eval_shipped_{v}" / "per_scene.csv"] for v in SHIPPED})
    chart(verdict, out / "verdict.png")

    # ---- brief fine-tuning from the shipped (a): training works ----
    # (c)'s view-specific ResNet18 starts from random weights here (no ImageNet file in the
    # demo; the report says so): not a warning worth printing in the demo's output.
    logging.getLogger("usplat_dr.model.hypernet.resnet").setLevel(logging.ERROR)
    runs, tuned = {}, {}
    for variant in ("baseline", "full"):
        run = out / f"train_{variant}"
        t = time.perf_counter()
        train(training_config(data, run, b, variant, PRESET, init=shipped[BASE]), resume=True)
        timings[f"fine-tuning {variant}"] = time.perf_counter() - t
        runs[variant] = run
        model, _ = load_model(run / "checkpoints" / "last.ckpt")
        tuned[variant] = evaluate(model, dataset, {"standard": indices["standard"]},
                                  out / f"eval_{variant}", label=f"fine-tuned {variant}",
                                  images_per_split=0)
    _curves(runs, out / "training_curves.png")

    t = time.perf_counter()
    worst = {v: worst_cases(out, b, v, shipped[SHIPPED[v]]) for v in ("baseline", "full")}
    timings["worst-case renders"] = time.perf_counter() - t
    t = time.perf_counter()
    bench_models = {BenchConfig(PRESET, v): load_model(shipped[SHIPPED[v]])[0]
                    for v in ("baseline", "full")}
    bench = write_results(measure(bench_models, data, b.size), b.size, out / "bench_demo")
    timings["speed/accuracy bench"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_start
    manifest = {e["name"]: e for e in json.loads((checkpoints / "manifest.json").read_text())}
    report = write_report(out, b, budget, summaries, timings, worst, bench,
                          {v: stability(r) for v, r in runs.items()}, verdict, tuned,
                          provenance([data]), {n: manifest[n] for n in
                                               (BASE, *SHIPPED.values())})
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


def worst_cases(out: Path, b: Budget, variant: str, checkpoint: Path) -> dict:
    """Per split, the comparison sheet of the scene with the lowest PSNR (from the shipped
    model's evaluation ``per_scene.csv``): ``{split: png path, split + "_psnr": its PSNR}``."""
    import csv

    import torch

    from usplat_dr.evaluation import load_example, load_model, save_comparison, synthetic_indices
    from usplat_dr.training import scene_args

    with open(out / f"eval_shipped_{variant}" / "per_scene.csv") as f:
        rows = list(csv.DictReader(f))
    model, _ = load_model(checkpoint)
    indices = synthetic_indices(out / "data")
    dataset = {"name": "synth", "roots": [str(out / "data")], "image_shape": [b.size, b.size]}
    found = {}
    for split in indices:
        mine = [r for r in rows if r["split"] == split]
        if not mine:
            continue
        worst = min(mine, key=lambda r: float(r["psnr"]))
        batch = load_example(dataset, indices[split], worst["scene"])
        with torch.no_grad():
            result = model(*scene_args(batch, torch.device("cpu")))
        found[split] = save_comparison(
            out / f"eval_shipped_{variant}" / "worst" / f"{split}_{worst['scene']}.png", batch,
            result)
        found[split + "_psnr"] = float(worst["psnr"])
    return found


def _label(variant: str, manifest: dict) -> str:
    if variant == "base":
        return f"(a) shipped `{BASE}` ({manifest[BASE]['steps']} steps)"
    e = manifest[SHIPPED[variant]]
    return f"{VARIANTS[variant]} `{e['name']}` ({e['steps']} steps)"


def _cells(m: dict) -> str:
    return f"{m['psnr']:.2f} / {m['ssim']:.3f} / {m['abs_rel']:.3f}"


def write_report(out: Path, b: Budget, budget: str, summaries: dict, timings: dict,
                 worst: dict, bench: dict, stable: dict, verdict: list, tuned: dict,
                 prov: dict, manifest: dict) -> Path:
    from usplat_dr.io import atomic_open
    from usplat_dr.verdict import table

    test = next(iter(summaries.values()))["splits"]["standard"]["scenes"]
    lines = [
        "# usplat-dr demo report", "",
        f"Budget `{budget}`: {b.test_scenes} fresh held-out scenes rendered by Mitsuba "
        f"({b.frames} frames, {b.size}x{b.size}; a seed none of the checkpoints was trained or "
        f"tested on), the shipped `{PRESET}` checkpoints evaluated on them with the field's "
        f"protocol, and a brief fine-tuning ({b.steps} steps on {b.train_scenes} other "
        f"scenes) from the shipped (a).", "",
        "## The shipped checkpoints on fresh scenes (standard split)", "",
        "| model | parameters | time per scene | peak memory | PSNR | SSIM | depth AbsRel |",
        "|---|---|---|---|---|---|---|"]
    for variant, s in summaries.items():
        std = s["splits"]["standard"]
        lines.append(f"| {_label(variant, manifest)} | {s['parameters'] / 1e6:.2f}M | "
                     f"{1000 * s['time_per_scene_s']:.0f} ms | {s['peak_memory_gib']:.2f} GiB "
                     f"| {std['psnr']:.2f} | {std['ssim']:.3f} | {std['abs_rel']:.3f} |")
    lines += ["", f"(b) and (c) were initialised from `{BASE}` (zero-initialised hypernetwork "
              f"outputs: they start exactly at it) and fine-tuned for the same steps, seed and "
              f"data as (a) continued, the control they are paired with. Time per scene: 2 "
              f"context views in, Gaussians and renders for every target (CPU, 2 threads). "
              f"LPIPS: unavailable (no VGG/LPIPS weight files in the demo). Training recipes "
              f"and data: `checkpoints/manifest.json`.", "",
              "## Verdict on view conditioning (these scenes, the shipped seed)", "",
              f"Paired per-scene differences against (a) continued over the {test} fresh "
              "scenes (the stress splits hold the scenes that qualify), with bootstrap 95% "
              "intervals over scenes. One fine-tuning seed: the interval does not cover seed "
              "variation; the multi-seed verdict (3 seeds x 60 scenes, "
              "`train/verdict_study.py`) is in BENCHMARKS.md, \"View conditioning: the "
              "verdict\".", "", table(verdict), "", "![verdict](verdict.png)", "",
              "## Per split (PSNR / SSIM / depth AbsRel)", "",
              "| split | scenes | " + " | ".join(_label(v, manifest) for v in summaries) + " |",
              "|---|---|" + "---|" * len(summaries)]
    first = next(iter(summaries.values()))
    for split, m in first["splits"].items():
        cells = [_cells(s["splits"][split]) for s in summaries.values()]
        lines.append(f"| {split} | {m['scenes']} | " + " | ".join(cells) + " |")
    lines += ["", "### Worst cases", "",
              "Per split, the held-out scene with the lowest PSNR (context views, ground truth, "
              "prediction, depth per target)."]
    for split in first["splits"]:
        for variant, w in worst.items():
            if split in w:
                lines.append(f"\n{VARIANTS[variant]}, {split}: {w[split].stem} "
                             f"({w[split + '_psnr']:.2f} dB)\n\n![{split}]"
                             f"({w[split].relative_to(out)})")
    lines += ["", "## Fine-tuning briefly from the shipped (a)", "",
              f"{b.steps} steps of (a) and (c) from `{BASE}` on the demo's {b.train_scenes} "
              f"training scenes (learning rate {FINETUNE_LR:g}, depth supervision as shipped; "
              "(c)'s view-specific ResNet18 starts from random weights, as in the shipped "
              "(c): no ImageNet weight file here), "
              "evaluated on the standard split: it shows that training runs; at this length it "
              "says nothing about the verdict.", "",
              "| model | PSNR / SSIM / AbsRel before | after |", "|---|---|---|"]
    for variant, s in tuned.items():
        lines.append(f"| {VARIANTS[variant]} | {_cells(summaries['base']['splits']['standard'])}"
                     f" | {_cells(s['splits']['standard'])} |")
    lines += ["", "![training curves](training_curves.png)", "", *_stability_lines(stable),
              "## Speed against accuracy", "",
              "The shipped (a) continued and (c), measured by `usplat bench`'s code on the "
              "standard split: Gaussian budgets (pruning per target before rasterising) at "
              f"{b.size}x{b.size} and a smaller render size.", "",
              "![speed against accuracy](bench_demo/bench.png)", "",
              (out / "bench_demo" / "bench.md").read_text().rstrip(), "",
              "Pruning (worst PSNR change over the models, mean fraction of Gaussians kept; on "
              "by default where it costs less than 0.05 dB):", "",
              "| pruning | worst PSNR change | kept | safe |", "|---|---|---|---|"]
    for name, p in sorted(bench["pruning"].items()):
        lines.append(f"| {name} | {p['worst_psnr_change_db']:+.3f} dB | "
                     f"{p['kept_fraction']:.2f} | {'yes' if p['safe'] else 'no'} |")
    full_bench = out / "bench" / "bench.md"
    if full_bench.is_file():
        lines += ["", "### Full `usplat bench` (all presets)", "",
                  "![usplat bench](bench/bench.png)", "", full_bench.read_text().rstrip()]
    lines += ["", "## Novel views", "",
              "Each row: context views, ground truth, prediction, predicted depth."]
    for variant in ("baseline", "full"):
        renders = sorted((out / f"eval_shipped_{variant}" / "renders" / "standard")
                         .glob("*.png"))[:2]
        for r in renders:
            lines.append(f"\n{VARIANTS[variant]}, {r.stem}:\n\n![{r.stem}]"
                         f"({r.relative_to(out)})")
    lines += ["", "## Where these numbers came from", "",
              "| | |", "|---|---|",
              *[f"| {k} | {v} |" for k, v in prov.items() if k != "data"],
              *[f"| data `{k}` | sha256 `{v}` |" for k, v in prov["data"].items()],
              *[f"| checkpoint `{n}` | sha256 `{e['sha256'][:16]}...`, {e['steps']} steps, "
                f"data: {e['data']} |" for n, e in manifest.items()],
              "", "Same command, same machine kind: docs/reproducibility.md says what is "
              "pinned (USPLAT_PORTABLE) and what can still differ.",
              "", "## Wall time", "", "| stage | seconds |", "|---|---|"]
    lines += [f"| {k} | {v:.0f} |" for k, v in timings.items()]
    path = out / "report.md"
    with atomic_open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
    return path
