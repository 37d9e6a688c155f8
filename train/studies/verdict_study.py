"""The view-conditioning verdict, multi-seed (the paper's protocol): from one trained (a),
fine-tune (a) on (the control), (b) and (c) for the same steps with each seed, evaluate all
of them on the same held-out scenes, and compare paired per-scene differences with bootstrap
95% intervals over scenes and seeds (``usplat_dr.evaluation.verdict``).

    python train/studies/verdict_study.py --init checkpoints/tiny_baseline.pt \
        --data outputs/big/train480 --eval-data outputs/big/test2000 \
        --seeds 0 1 2 --steps 1000 --out outputs/verdict --jobs 2

Each run trains and evaluates in its own process with one thread (``--jobs`` at a time) and
is resumable: a second call skips finished runs and resumes killed ones. Writes
``<out>/verdict.md``, ``verdict.json``, ``verdict.png``, ``labels.json`` (per split, (c) - (a)
on PSNR with both intervals and the pre-registered rule's label) and ``runs.json`` (steps and
seconds per step of every run: the equal-wall-time view); ``--also-eval`` repeats the
comparison on more held-out sets (``verdict_<set>.md``), the same runs on other scenes.
"""

import argparse
import json
import logging
import shlex
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import usplat_dr  # noqa: F401  (libLLVM before drjit)
from usplat_dr import portable

portable.enable()  # AVX2 code paths, as the usplat command (before torch is imported)

CONFIG = "synthetic_tiny_depth.yaml"  # packaged (usplat_dr/configs/)


def run_name(variant: str, seed: int) -> str:
    return f"{variant}_seed{seed}"


def run_one(args, variant: str, seed: int) -> dict:
    """Train and evaluate one (variant, seed) in this process, one thread. ``variant``
    ``baseline_wall`` is (a) trained on for ``--wall-ratio`` times the steps: (a) at the
    wall time (c) takes."""
    import torch

    from usplat_dr.config import load_config
    from usplat_dr.evaluation import evaluate, synthetic_indices
    from usplat_dr.training import train
    from usplat_dr.training.checkpoints import load_model

    run = Path(args.out) / run_name(variant, seed)
    steps = round(args.steps * args.wall_ratio) if variant == "baseline_wall" else args.steps
    model_variant = "baseline" if variant == "baseline_wall" else variant
    done = run / "eval" / "per_scene.csv"
    if done.is_file():
        return json.loads((run / "run.json").read_text())
    cfg = load_config([CONFIG], [
        f"dataset.roots=[{args.data}]", f"output_dir={run}", f"model.variant={model_variant}",
        f"model.init_from={args.init}", f"seed={seed}", f"dataset.overrides.seed={seed}",
        f"train.steps={steps}", f"optimizer.lr={args.lr}",
        f"optimizer.warm_up_fraction={args.warm_up}",
        f"optimizer.hyper_lr_scale={args.hyper_lr_scale}", "threads=1", "train.progress=false",
        *([f"model.overrides.delta_init_std={args.delta_init_std}"]
          if model_variant == "full" and args.delta_init_std else []),
        *([f"model.overrides.{o}" for o in args.full_override] if model_variant == "full"
          else []),
        *[f"model.overrides.{o}" for o in args.model_override],
        f"train.checkpoint_every={max(50, steps // 10)}", f"train.validate_every={steps}"])
    t0 = time.perf_counter()
    result = train(cfg, resume=True)
    seconds = time.perf_counter() - t0
    model, step = load_model(run / "checkpoints" / "last.ckpt")
    torch.set_num_threads(1)
    summary = evaluate(model, {"name": "synth", "roots": [args.eval_data],
                               "image_shape": [args.size, args.size]},
                       synthetic_indices(args.eval_data), run / "eval", images_per_split=2,
                       progress=False, label=f"{variant} seed {seed}")
    rows = list(csv_rows(run / "metrics.csv"))
    info = {"variant": variant, "seed": seed, "steps": step, "train_seconds": seconds,
            "steps_per_s": float(rows[-1]["steps_per_s"]) if rows else None,
            "final": result, "splits": summary["splits"]}
    (run / "run.json").write_text(json.dumps(info, indent=1))
    return info


def csv_rows(path: Path):
    import csv

    with open(path) as f:
        yield from csv.DictReader(f)


def main(argv=None) -> int:
    # here, not at the top: the model loads torch, after portable.enable() and only when run
    from usplat_dr.model.uniquesplat import VARIANTS

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--init", required=True, help="the trained (a) all runs start from")
    p.add_argument("--data", required=True, help="training set root")
    p.add_argument("--eval-data", required=True, help="held-out synthetic set root")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    p.add_argument("--steps", type=int, default=1000, help="fine-tuning steps per run")
    p.add_argument("--lr", type=float, default=2e-4, help="peak learning rate")
    p.add_argument("--warm-up", type=float, default=0.05, help="warm-up fraction")
    p.add_argument("--hyper-lr-scale", type=float, default=1.0,
                   help="learning rate of the hypernetwork branches over --lr "
                        "(optimizer.hyper_lr_scale; (a) has none)")
    p.add_argument("--delta-init-std", type=float, default=0.0,
                   help="(c)'s H_s initialisation (model.overrides.delta_init_std; 0: Delta W "
                        "starts at exactly 0)")
    p.add_argument("--full-override", nargs="+", default=[], metavar="KEY=VALUE",
                   help="fields of (c)'s model config, e.g. delta_rank=16 "
                        "'specific_layers=[to_gaussians.0,to_gaussians.2]' "
                        "(model.overrides.KEY=VALUE; only the full variant's runs)")
    p.add_argument("--model-override", nargs="+", default=[], metavar="KEY=VALUE",
                   help="fields of every run's model config, e.g. "
                        "primary.colour_sh_degree=0 (model.overrides.KEY=VALUE)")
    p.add_argument("--kinds", nargs="+", default=[], choices=["indoor", "outdoor", "object"],
                   help="compare on the held-out scenes of these kinds only (the cross-kind "
                        "split: trained on one kind, judged on the others)")
    p.add_argument("--size", type=int, default=64)
    p.add_argument("--out", default="outputs/verdict")
    p.add_argument("--jobs", type=int, default=2, help="runs at a time (one thread each)")
    p.add_argument("--wall-ratio", type=float, default=None,
                   help="also train (a) for this many times the steps: (a) at (c)'s wall time "
                        "(the ratio of their seconds per step, train/bench/training.py)")
    p.add_argument("--also-eval", nargs="+", default=[], metavar="DATA",
                   help="more held-out sets: every run is evaluated on each as well (in "
                        "<run>/eval_<folder name>) and each gets its own verdict_<folder "
                        "name>.md / .png")
    p.add_argument("--register", metavar="FILE",
                   help="also record the standard split's labels (both arms) in FILE under "
                        "--set-name, keeping its other sets (checkpoints/verdict.json: what "
                        "the demo prints)")
    p.add_argument("--set-name", default=None,
                   help="the held-out set's name in --register (default: the --eval-data "
                        "folder's name, standard split)")
    p.add_argument("--job", nargs=2, metavar=("VARIANT", "SEED"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    names = [Path(d).resolve().name for d in (args.eval_data, *args.also_eval)]
    if len(set(names)) != len(names):
        p.error(f"--eval-data and --also-eval need distinct folder names (their results are "
                f"kept by name: eval_<name>), got {names}")
    for flag, values in (("--full-override", args.full_override),
                         ("--model-override", args.model_override)):
        bad = [o for o in values if "=" not in o]
        if bad:
            p.error(f"{flag} takes KEY=VALUE pairs (fields of UniqueSplatCfg), got {bad}")
    if "baseline" not in args.variants:
        p.error("--variants must include baseline (the control every variant is paired with)")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.job:  # a worker: one run
        run_one(args, args.job[0], int(args.job[1]))
        return 0

    def launch(job):
        variant, seed = job
        log = out / f"{variant}_seed{seed}.log"
        with open(log, "a") as f:
            code = subprocess.call([sys.executable, __file__, *(argv or sys.argv[1:]),
                                    "--job", variant, str(seed)], stdout=f, stderr=f)
        print(f"{variant} seed {seed}: {'done' if code == 0 else f'FAILED ({log})'}",
              flush=True)
        return code

    jobs = [(v, s) for s in args.seeds for v in args.variants]
    if args.wall_ratio:
        jobs += [("baseline_wall", s) for s in args.seeds]
    with ThreadPoolExecutor(args.jobs) as pool:
        codes = list(pool.map(launch, jobs))
    if any(codes):
        return 1
    infos = [json.loads((out / run_name(v, s) / "run.json").read_text()) for v, s in jobs]
    from usplat_dr.io import write_json

    write_json(out / "runs.json", infos)
    speed = {v: sum(i["train_seconds"] for i in infos if i["variant"] == v)
             / sum(i["steps"] for i in infos if i["variant"] == v)
             for v in {v for v, _ in jobs}}
    text = write_verdict(args, out, "eval", "", f"`{args.eval_data}`")
    text += ("Seconds per training step (one thread, including start-up; a resumed run counts "
             "its last segment only): "
             + ", ".join(f"{v} {s:.3f}" for v, s in sorted(speed.items())) + "\n")
    (out / "verdict.md").write_text(text)
    print(text)
    if args.register:
        register(args, out)
    for data in args.also_eval:
        name = Path(data).resolve().name
        evaluate_again(args, out, jobs, data, f"eval_{name}")
        text = write_verdict(args, out, f"eval_{name}", f"_{name}", f"`{data}`")
        (out / f"verdict_{name}.md").write_text(text)
        print(text)
    return 0


def register(args, out: Path) -> None:
    """Write the standard split's PSNR labels of this study into ``--register``'s file, one
    entry per arm, replacing earlier entries of the same set and arm and keeping the others
    (a later call with more seeds and no wall-time arm keeps the earlier wall-time row)."""
    import datetime

    from usplat_dr.evaluation.verdict import REFUTE, SUPPORT
    from usplat_dr.io import write_json

    name = args.set_name or (f"standard split of {Path(args.eval_data).resolve().name}"
                             + (f", {' and '.join(args.kinds)} scenes" if args.kinds else ""))
    path = Path(args.register)
    old = json.loads(path.read_text()) if path.is_file() else {"sets": []}
    argv, kept = sys.argv[1:], []
    for i, a in enumerate(argv):  # the command that made the rows, without --register FILE
        if a == "--register" or (i and argv[i - 1] == "--register") or a.startswith("--register="):
            continue
        kept.append(a)
    command = "python train/studies/verdict_study.py " + shlex.join(kept)
    rows = [{"set": name, **{k: r[k] for k in ("arm", "mean", "low", "high", "seed_low",
                                                 "seed_high", "seeds", "scenes", "label")},
             **({"branch_live": r["branch_live"]} if r.get("branch_live") else {}),
             "init": args.init, "command": command}
            for r in json.loads((out / "labels.json").read_text()) if r["split"] == "standard"]
    write_json(path, {
        "date": datetime.date.today().isoformat(),
        "rule": f"supports if (c) - (a) >= +{SUPPORT} dB with the seed-level lower bound > 0; "
                f"refutes if the seed-level upper bound < +{REFUTE} dB; else inconclusive",
        "protocol": "(a) continued and (c) fine-tuned from the same trained (a) (each row's "
                    "init) for the same steps, seeds and data; PSNR on the held-out set's "
                    "standard split",
        "sets": [e for e in old["sets"]
                 if (e["set"], e.get("arm")) not in {(r["set"], r["arm"]) for r in rows}]
                + rows})
    print(f"registered {len(rows)} rows for {name!r} in {path}")


def evaluate_again(args, out: Path, jobs, data: str, eval_name: str) -> None:
    """Evaluate every finished run's last checkpoint on another held-out set (one thread,
    in this process; runs already evaluated there are skipped)."""
    import drjit as dr
    import torch

    from usplat_dr.evaluation import evaluate, synthetic_indices
    from usplat_dr.training.checkpoints import load_model

    torch.set_num_threads(1)
    dr.set_thread_count(1)
    for variant, seed in jobs:
        run = out / run_name(variant, seed)
        if (run / eval_name / "per_scene.csv").is_file():
            continue
        model, _ = load_model(run / "checkpoints" / "last.ckpt")
        evaluate(model, {"name": "synth", "roots": [data], "image_shape": [args.size, args.size]},
                 synthetic_indices(data), run / eval_name, images_per_split=2, progress=False,
                 label=f"{variant} seed {seed} on {data}")
        print(f"{variant} seed {seed}: evaluated on {data}", flush=True)


def write_verdict(args, out: Path, eval_name: str, suffix: str, where: str) -> str:
    """The paired comparison of the runs' evaluations in ``<run>/<eval_name>``: writes
    ``verdict<suffix>.json`` and ``.png``, returns the Markdown tables."""
    from usplat_dr.evaluation.verdict import as_dicts, chart, compare, table
    from usplat_dr.evaluation.view_specificity import LIVE_BOUND_DB, manipulation_check
    from usplat_dr.io import write_json

    def csvs(v):
        return [out / run_name(v, s) / eval_name / "per_scene.csv" for s in args.seeds]

    prefixes = tuple(f"{k}_" for k in args.kinds)
    if args.kinds:
        where += f" ({' and '.join(args.kinds)} scenes only)"
    rows = compare({v: csvs(v) for v in args.variants}, scene_prefixes=prefixes)
    wall_rows = (compare({"baseline": csvs("baseline_wall"), "full": csvs("full")},
                         scene_prefixes=prefixes)
                 if args.wall_ratio and "full" in args.variants else [])
    write_json(out / f"verdict{suffix}.json", {"args": vars(args), "held_out": where,
                                               "rows": as_dicts(rows),
                                               "equal_wall_time_rows": as_dicts(wall_rows)})
    if rows:  # none when only (a) ran (train/studies/sh_control.py compares two such studies)
        chart(rows, out / f"verdict{suffix}.png")
    # the pre-registered rule's label per split, (c) - (a) on PSNR (checkpoints/verdict.json
    # holds these for the shipped protocol; the demo prints them)
    # The manipulation check: each (c) run's view-specificity meter on the standard split
    checks = {s: manipulation_check(out / run_name("full", s) / eval_name / "per_scene.csv")
              for s in args.seeds} if "full" in args.variants else {}
    live = [s for s, c in checks.items() if c and c["live"]]
    branch_live = (f"{len(live)} of {len(checks)} seeds live (mean |PSNR(own) - PSNR(scene "
                   f"mean)| >= {LIVE_BOUND_DB} dB)") if checks else None
    write_json(out / f"labels{suffix}.json", [
        {"held_out": where, "split": r.split, "arm": arm, "mean": r.mean, "low": r.low,
         "high": r.high, "seed_low": r.seed_low, "seed_high": r.seed_high, "seeds": r.seeds,
         "scenes": r.scenes, "label": r.label, "branch_live": branch_live,
         "counts": bool(checks) and len(live) == len(checks)}
        for arm, rs in (("equal steps", rows), ("equal wall time", wall_rows))
        for r in rs if r.metric == "psnr" and r.variant == "full"])
    text = (f"# Verdict: {len(args.seeds)} seeds x {args.steps} fine-tuning steps from "
            f"`{args.init}`, evaluated on {where}\n\n")
    if checks:
        text += ("## Manipulation check: is each (c)'s view-specific branch live?\n\n"
                 "| seed | scenes | Delta W spread (of norm W) | mean abs PSNR(own) - PSNR(scene "
                 "mean) [95% t] | live? |\n|---|---|---|---|---|\n")
        for s, c in checks.items():
            text += (f"| {s} | {c['scenes']} | {c['spread_rel_w']:.1e} | {c['psnr_abs_db']:.4f} "
                     f"dB [{c['low']:.4f}, {c['high']:.4f}] | {'yes' if c['live'] else 'no'} |\n"
                     if c else f"| {s} | | | no meter in its evaluation | no |\n")
        text += (f"\n{branch_live}: " + ("the labels below judge per-view weights.\n\n"
                 if len(live) == len(checks) else "a (c) whose branch is not live is (b) plus a "
                 "constant per scene; the labels below test the protocol, not per-view "
                 "weights, and do not count.\n\n"))
    text += f"## Equal steps\n\n{table(rows)}\n\n"
    if wall_rows:
        text += (f"## Equal wall time: (c) against (a) trained {args.wall_ratio:g}x the "
                 f"steps\n\n{table(wall_rows)}\n\n")
    return text + f"![](verdict{suffix}.png)\n\n"


if __name__ == "__main__":
    sys.exit(main())
