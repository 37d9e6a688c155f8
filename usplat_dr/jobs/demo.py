"""``usplat demo``: the main job. On a fresh machine, with no arguments: render fresh held-out
synthetic scenes with Mitsuba, evaluate the shipped checkpoints (``checkpoints/manifest.json``:
the trained primary network (a), and (a) continued, (b) and (c) fine-tuned from it by the
paper's protocol) with the field's protocol on them and their stress splits, give the verdict
on view conditioning with bootstrap intervals over the scenes, fine-tune (a) and (c) briefly
from the shipped (a) to show that training works, and write a report folder (``report.md``
with PNGs: the verdict chart, novel views next to ground truth, depth maps, training curves,
worst cases, speed against accuracy, and where the numbers came from).

Recipes: ``full`` (``usplat_dr.DEMO_MINUTES`` minutes on a 2-core CPU, by host;
BENCHMARKS.md) and ``quick`` (a
minute or two, for CI).
The multi-seed verdict (fine-tuning seeds x held-out scenes) is
``train/studies/verdict_study.py``; its result is in train/studies/LOG.md.
"""

import argparse
import csv
import json
import logging
import time
from pathlib import Path

import torch

from usplat_dr.data.types import model_inputs
from usplat_dr.evaluation import evaluate, load_example, synthetic_indices
from usplat_dr.evaluation.figures import save_comparison
from usplat_dr.evaluation.provenance import provenance
from usplat_dr.evaluation.speed import BenchConfig, measure
from usplat_dr.evaluation.verdict import chart as verdict_chart
from usplat_dr.evaluation.verdict import compare
from usplat_dr.jobs.arguments import non_negative_int
from usplat_dr.jobs.report import DemoResults, write_report, write_results
from usplat_dr.model.auto_budget import AutoBudget
from usplat_dr.training import train
from usplat_dr.training.checkpoints import (
    BASE,
    BEYOND,
    BUDGETED,
    CHECKPOINTS,
    LIVE,
    SHIPPED,
    load_model,
    registered_verdict,
    shipped_checkpoints,
)
from usplat_dr.training.recipes import PRESET, RECIPES, RunRecipe, ensure_data, training_config
from usplat_dr.training.run_log import curves, stability

#: The Gaussian budgets of the demo's speed/accuracy bench (fractions of the Gaussians, each
#: ranked by the budget stage's learned importance (the BUDGETED add-ons, unbudgeted the very
#: SHIPPED models), its untrained start (dither), the screen footprint, and the opacity and
#: random controls); the first is also the one whose allocation the report shows.
BUDGET_FRACTIONS = (0.1, 0.3)

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="outputs/demo",
                   help="the report folder (report.md, its PNGs, the data and runs)")
    p.add_argument("--quick", action="store_true", help="the quick recipe (CI): a minute or two")
    p.add_argument("--jobs", type=non_negative_int, default=0,
                   help="Mitsuba worker processes (0: auto)")


def run(args: argparse.Namespace) -> int:
    run_demo(args.out, "quick" if args.quick else "full", jobs=args.jobs)
    return 0


def run_demo(out: str | Path = "outputs/demo", recipe: str = "full", seed: int = 0,
             jobs: int = 0, checkpoints: Path = CHECKPOINTS) -> Path:
    """Run the whole job; returns the path of ``report.md``."""
    if recipe not in RECIPES:
        raise ValueError(f"recipe must be one of {sorted(RECIPES)}, got {recipe!r}")
    b = RECIPES[recipe]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    shipped = shipped_checkpoints(checkpoints)
    missing = sorted({BASE, *SHIPPED.values(), *BUDGETED.values(), LIVE, BEYOND}
                     - set(shipped))
    if missing:
        raise FileNotFoundError(f"the manifest in {checkpoints} lacks {missing}")
    t_start = time.perf_counter()
    timings = {}
    if ensure_data(out, recipe, seed, jobs):
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
                                      label=variant, view_meter=("standard",))
        timings[f"evaluation shipped {variant}"] = time.perf_counter() - t
    verdict = compare({v: [out / f"eval_shipped_{v}" / "per_scene.csv"] for v in SHIPPED})
    t = time.perf_counter()  # the live (c): its meter, and its standard-split numbers
    live = evaluate(load_model(shipped[LIVE])[0], dataset, {"standard": indices["standard"]},
                    out / "eval_shipped_live", label="live (c)", view_meter=("standard",),
                    images_per_split=0)
    timings["evaluation shipped live (c)"] = time.perf_counter() - t
    t = time.perf_counter()  # the (c) trained with extrapolated targets: where it varies
    wanted = [s for s in ("standard", "extrapolation") if s in indices]
    beyond = evaluate(load_model(shipped[BEYOND])[0], dataset, {s: indices[s] for s in wanted},
                      out / "eval_shipped_beyond", label="(c) beyond", view_meter=True,
                      images_per_split=0)
    timings["evaluation shipped (c) trained beyond the context"] = time.perf_counter() - t
    verdict_chart(verdict, out / "verdict.png")

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
    curves(runs, out / "training_curves.png")

    t = time.perf_counter()
    worst = {v: worst_cases(out, b, v, shipped[SHIPPED[v]]) for v in ("baseline", "full")}
    timings["worst-case renders"] = time.perf_counter() - t
    t = time.perf_counter()
    bench_models = {BenchConfig(PRESET, v): load_model(shipped[BUDGETED[v]])[0]
                    for v in ("baseline", "full")}
    bench = write_results(measure(bench_models, data, b.size, gaussians=BUDGET_FRACTIONS),
                          b.size, out / "bench_demo")
    timings["speed/accuracy bench"] = time.perf_counter() - t
    t = time.perf_counter()  # where the smallest budget goes in (c), scene by scene
    allocation = evaluate(bench_models[BenchConfig(PRESET, "full")], dataset,
                          {"standard": indices["standard"]}, out / "eval_budget_full",
                          label="budget (c)", budget=BUDGET_FRACTIONS[0], images_per_split=2)
    timings["where the budget goes"] = time.perf_counter() - t
    t = time.perf_counter()  # each scene's own count, against all Gaussians
    auto = evaluate(bench_models[BenchConfig(PRESET, "full")], dataset,
                    {"standard": indices["standard"]}, out / "eval_auto_full",
                    label="auto (c)", budget=AutoBudget(), images_per_split=0)
    timings["automatic count"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_start
    manifest = {e["name"]: e for e in json.loads((checkpoints / "manifest.json").read_text())}
    report = write_report(DemoResults(
        out=out, recipe=b, recipe_name=recipe, summaries=summaries, timings=timings,
        worst=worst, bench=bench, stable={v: stability(r) for v, r in runs.items()},
        verdict=verdict, tuned=tuned, provenance=provenance([data]), allocation=allocation,
        auto=auto,
        manifest={n: manifest[n]
                  for n in (BASE, *SHIPPED.values(), *BUDGETED.values(), LIVE, BEYOND)},
        registered=registered_verdict(checkpoints), live=live, beyond=beyond))
    print(f"report: {report}")
    return report


def worst_cases(out: Path, b: RunRecipe, variant: str, checkpoint: Path) -> dict:
    """Per split, the comparison sheet of the scene with the lowest PSNR (from the shipped
    model's evaluation ``per_scene.csv``): ``{split: png path, split + "_psnr": its PSNR}``."""
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
            result = model(*model_inputs(batch, torch.device("cpu")))
        found[split] = save_comparison(out / f"eval_shipped_{variant}" / "worst", batch, result,
                                       prefix=f"{split}_")
        found[split + "_psnr"] = float(worst["psnr"])
    return found
