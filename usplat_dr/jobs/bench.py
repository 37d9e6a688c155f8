"""``usplat bench``: speed against accuracy, measured in one run on one machine.

Trains (or reuses) each configuration on the demo's synthetic training set (``usplat demo``'s
data and recipe; the demo's own runs are reused), then measures on the held-out scenes of the
standard split, interleaving configurations scene by scene so that a busy machine slows all of
them alike:

- time per rendered novel view: (model time for the scene + its targets' pruning and
  rendering) / number of targets, i.e. the encoder's share amortised over the scene's targets;
  wall time and process CPU time, median over scenes (the first scene warms kernels up); and
  the rendering's share alone (pruning and rasterising, or rasterising a budget's K: what
  falls with the Gaussians where the encoder's share does not);
- peak memory of the model's forward pass (CPU: the rise of the process's peak RSS, reset per
  measurement through ``/proc/self/clear_refs``; CUDA: ``max_memory_allocated``);
- parameters, Gaussians rendered per view, and accuracy: PSNR, SSIM, depth AbsRel.

Axes: configurations (size preset x variant), pruning (``usplat_dr.render.prune.PRUNES``:
everything, exact culling, merging near-duplicates) at the training resolution, render
resolutions (default pruning), and with ``--gaussians`` the Gaussian budget chosen at inference
(``UniqueSplat.forward(budget=GaussianBudget(...))``, model/budget.py) at each count or
fraction, ranked by each of ``--rank-by``: ``learned`` (models with an importance head),
``dither`` (its untrained start), ``footprint`` (opacity x screen area, per target camera),
``opacity`` and ``random``, the controls; ``--splits`` adds the stress splits (rows per
split). Writes ``bench.csv``, ``bench.png`` (accuracy against time per view with the Pareto
front; accuracy against Gaussians rendered, with its own front), ``bench.md`` (the table)
and ``summary.json`` (the smallest configuration within 0.3 dB of the best, which pruning
settings cost less than 0.05 dB everywhere, and each budget's worst PSNR change).
"""

import argparse
import json
import logging
from pathlib import Path

from usplat_dr.evaluation.speed import DEFAULT_CONFIGS, BenchConfig, measure
from usplat_dr.jobs.arguments import (
    DEVICE_HELP,
    RenamedOption,
    gaussians_argument,
    non_negative_int,
)
from usplat_dr.jobs.report import bench_table, write_results
from usplat_dr.model.budget import RANKINGS
from usplat_dr.render.prune import PRUNES
from usplat_dr.training import train
from usplat_dr.training.checkpoints import BASE, load_models, shipped_checkpoints
from usplat_dr.training.distributed import set_threads
from usplat_dr.training.loader import load
from usplat_dr.training.recipes import RECIPES, ensure_data, training_config

log = logging.getLogger(__name__)

def train_configs(out: Path, recipe: str, configs, seed: int = 0, jobs: int = 0) -> dict:
    """Train what is missing (a finished run is reused; an interrupted one resumes)."""
    ensure_data(out, recipe, seed, jobs)
    b = RECIPES[recipe]
    try:  # the tiny preset fine-tunes from the shipped (a), as the demo does
        base = shipped_checkpoints().get(BASE)
    except FileNotFoundError:
        base = None
    runs = {}
    for c in configs:
        run = c.run_dir(out)
        log.info("bench: training %s in %s", c.label, run)
        init = base if c.preset == "tiny" else None
        train(training_config(out / "data", run, b, c.variant, preset=c.preset, init=init),
              resume=True)
        runs[c] = run
    return runs


def run_bench(out: str | Path = "outputs/demo", recipe: str = "full", configs=DEFAULT_CONFIGS,
              render_sizes=None, prunes=None, device: str = "cpu", seed: int = 0,
              jobs: int = 0, gaussians=(), rank_by=RANKINGS, splits=("standard",),
              checkpoints: dict | None = None) -> dict:
    """Train what is missing, measure, write ``out/bench/``; returns the decisions."""
    if recipe not in RECIPES:
        raise ValueError(f"recipe must be one of {sorted(RECIPES)}, got {recipe!r}")
    out = Path(out)
    size = RECIPES[recipe].size
    if render_sizes and max(render_sizes) > size:
        raise ValueError(f"render sizes {render_sizes} exceed the data's {size}x{size} (the "
                         f"ground truth would be upsampled); use sizes <= {size}")
    runs = train_configs(out, recipe, configs, seed, jobs)
    models = load_models(runs, device)
    for config, path in (checkpoints or {}).items():  # --checkpoint PRESET:VARIANT:TAG=PATH
        models[config] = load(path, device)
    rows = measure(models, out / "data", size, render_sizes, prunes, device,
                   gaussians=gaussians, rank_by=rank_by, splits=splits)
    decision = write_results(rows, size, out / "bench")
    print(bench_table(rows))
    print(json.dumps(decision, indent=1))
    print(f"wrote {out / 'bench'} (bench.csv, bench.png, bench.md, summary.json)")
    return decision


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="outputs/demo", help="the demo folder (its data and runs "
                   "are shared)")
    p.add_argument("--configs", type=configs_argument, default=DEFAULT_CONFIGS,
                   help="comma-separated preset:variant, e.g. tiny:a,tiny:c,small:c, or none "
                   "(only the --checkpoint models) (default: tiny a/b/c, small c, paper c)")
    p.add_argument("--prunes", type=prunes_argument, default=PRUNES,
                   help="comma-separated pruning settings (default: all, cull, cull+merge1px, "
                   "cull+merge2px)")
    p.add_argument("--render-sizes", type=sizes_argument, default=None,
                   help="comma-separated render sizes <= the data's (default: half and full)")
    p.add_argument("--gaussians", "--fractions", dest="gaussians", type=gaussians_list,
                   default=(), action=RenamedOption, metavar="K[,K...]",
                   help="Gaussian budgets chosen at inference, each a count (5000) or a "
                   "fraction (0.3 or 30%%) of each target's Gaussians, comma-separated, e.g. "
                   "0.05,0.1,0.3,0.5 (default: none)")
    p.add_argument("--rank-by", type=rank_by_argument, default=RANKINGS,
                   help="comma-separated rankings of the budget: learned (models with an "
                   "importance head), dither, footprint, opacity, random (default: all)")
    p.add_argument("--splits", type=lambda t: tuple(t.split(",")), default=("standard",),
                   help="comma-separated splits of the demo's data, e.g. standard,"
                   "extrapolation (default: standard; the decisions use the first)")
    p.add_argument("--checkpoint", dest="checkpoints", action="append", default=[],
                   type=checkpoint_argument, metavar="PRESET:VARIANT:TAG=PATH",
                   help="also measure this checkpoint (a file or a shipped name), labelled "
                   "e.g. 'tiny (c) budget' for tiny:c:budget=...; repeatable")
    p.add_argument("--quick", action="store_true", help="the demo's quick recipe (CI)")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                   help=DEVICE_HELP)
    p.add_argument("--jobs", type=non_negative_int, default=0,
                   help="Mitsuba worker processes (0: auto)")
    p.add_argument("--threads", type=non_negative_int, default=0,
                   help="CPU threads of torch and Dr.Jit for the measurements (0: one per "
                   "core other processes leave free, or USPLAT_THREADS)")


def gaussians_list(text: str) -> tuple[float | int, ...]:
    """``--gaussians``: comma-separated budgets, each as ``usplat eval --gaussians`` takes one.

    Examples:
        >>> gaussians_list("0.1,30%,5000")
        (0.1, 0.3, 5000)
    """
    return tuple(gaussians_argument(t) for t in text.split(","))


def rank_by_argument(text: str) -> tuple[str, ...]:
    """``--rank-by``: comma-separated names of ``RANKINGS``."""
    unknown = sorted(set(text.split(",")) - set(RANKINGS))
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown {unknown}; choose from {list(RANKINGS)}")
    return tuple(text.split(","))


def checkpoint_argument(text: str) -> tuple[BenchConfig, str]:
    """``--checkpoint``: ``preset:variant:tag=path``."""
    spec, sep, path = text.partition("=")
    preset, _, rest = spec.partition(":")
    variant, _, tag = rest.partition(":")
    if not sep or not path or not tag:
        raise argparse.ArgumentTypeError(f"must be PRESET:VARIANT:TAG=PATH (e.g. "
                                         f"tiny:c:budget=outputs/tiny_full_budget/checkpoints/"
                                         f"last.ckpt), got {text!r}")
    try:
        return BenchConfig.parse(f"{preset}:{variant}", tag), path
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from e


def configs_argument(text: str) -> tuple[BenchConfig, ...]:
    """``--configs``: comma-separated ``preset:variant``, or ``none``."""
    if text == "none":
        return ()
    try:
        return tuple(BenchConfig.parse(c) for c in text.split(","))
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from e


def prunes_argument(text: str) -> dict:
    """``--prunes``: comma-separated names of ``PRUNES``."""
    unknown = sorted(set(text.split(",")) - set(PRUNES))
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown {unknown}; choose from {list(PRUNES)}")
    return {k: PRUNES[k] for k in text.split(",")}


def sizes_argument(text: str) -> list[int]:
    """``--render-sizes``: comma-separated positive ints."""
    try:
        sizes = [int(s) for s in text.split(",")]
    except ValueError:
        sizes = []
    if not sizes or min(sizes) < 1:
        raise argparse.ArgumentTypeError(f"must be comma-separated integers >= 1, got {text!r}")
    return sizes


def run(args: argparse.Namespace) -> int:
    if not args.configs and not args.checkpoints:
        raise ValueError("--configs none measures the --checkpoint models only: give at least "
                         "one --checkpoint PRESET:VARIANT:TAG=PATH")
    if args.threads:
        set_threads(args.threads, args.device)
    run_bench(args.out, "quick" if args.quick else "full", args.configs, args.render_sizes,
              args.prunes, device=args.device, jobs=args.jobs, gaussians=args.gaussians,
              rank_by=args.rank_by, splits=args.splits, checkpoints=dict(args.checkpoints))
    return 0
