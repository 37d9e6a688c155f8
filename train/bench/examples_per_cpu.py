"""Examples per CPU-second and held-out PSNR per CPU-hour of the tiny (a) recipe
(``synthetic_tiny_depth.yaml``, variant baseline, 64x64, 2 context + 4 target views) under
different process shapes: threads per process and scenes per step (``data_loader.batch_size``).

An *arm* is named ``t<threads>b<batch>`` with an optional ``lr<value>`` and ``p`` (portable
numerics, ``usplat``'s default: torch and Dr.Jit pinned to AVX2; without it, this benchmark's
processes leave them free), e.g. ``t2b1`` (two threads, one scene a step: the recipe as ``usplat
train`` ran it by default on a 2-core machine) or ``t1b4lr2e-3``. An *example* is one training
scene with its context pair and target views; CPU time is the process's (every thread, spinning
included), which is what a machine's cores give to the run.

    # 1. examples per CPU-second, arms interleaved step by step in one process per thread count
    python train/bench/examples_per_cpu.py throughput --data outputs/big/train480 \\
        --arms t2b1 t1b1 t1b2 t1b4 --steps 12
    # 2. one arm trained from scratch for a number of steps, a checkpoint kept every 1/6th
    python train/bench/examples_per_cpu.py train --data outputs/big/train480 --arm t1b4 \\
        --steps 2000 --out outputs/epc
    # 3. the kept checkpoints on held-out scenes, against each run's CPU time: a table and chart
    python train/bench/examples_per_cpu.py chart --runs outputs/epc \\
        --eval-data outputs/big/test2000 --baseline t2b1 --out train/bench/examples_per_cpu

``train`` resumes a killed run from its last checkpoint (``cpu_s`` in metrics.csv counts on
from the checkpoint's row; the killed process's work past it is not counted). Results:
train/bench/README.md, "Examples per CPU-second".
"""

import argparse
import csv
import json
import os
import re
import shutil
import subprocess
import sys
from functools import partial
from pathlib import Path

import torch  # users' order: torch first (usplat_dr then cannot shorten OpenMP's spin)

import usplat_dr  # noqa: F401  (libLLVM before drjit)
from usplat_dr import portable

RECIPE = "synthetic_tiny_depth.yaml"
ARM = re.compile(r"^t(?P<threads>\d+)b(?P<batch>\d+)(?:lr(?P<lr>[0-9.eE+-]+?))?(?P<p>p)?$")


def parse_arm(name: str) -> dict:
    """``t1b4lr2e-3`` -> threads 1, batch 4, lr 0.002 (None: the recipe's), not portable."""
    m = ARM.match(name)
    if not m:
        raise argparse.ArgumentTypeError(
            f"arm {name!r} is not t<threads>b<batch>[lr<value>], e.g. t2b1 or t1b4lr2e-3")
    return {"name": name, "threads": int(m["threads"]), "batch": int(m["batch"]),
            "lr": float(m["lr"]) if m["lr"] else None, "portable": bool(m["p"])}


def overrides(arm: dict, data: str, out: str, steps: int, seed: int) -> list[str]:
    """The recipe's config overrides for ``arm``: from scratch, (a), one checkpoint per sixth
    of the run, one validation render at the end."""
    over = [f"dataset.roots=[{data}]", f"output_dir={out}", "model.variant=baseline",
            f"threads={arm['threads']}", f"data_loader.batch_size={arm['batch']}",
            f"seed={seed}", f"train.steps={steps}", f"train.checkpoint_every={max(steps // 6, 1)}",
            f"train.validate_every={steps}", "train.log_every=10", "keep_cores_awake=false"]
    if arm["lr"] is not None:
        over.append(f"optimizer.lr={arm['lr']}")
    return over


def throughput(args) -> None:
    """Median wall and CPU time per step of each arm; arms of one thread count and numerics
    share a process (interleaved step by step, ``usplat_dr.evaluation.timing.interleaved``: a
    busy machine slows them alike), whose line naming the machine is printed with the table."""
    arms = [parse_arm(a) for a in args.arms]
    groups: dict[tuple, list] = {}
    for a in arms:
        groups.setdefault((a["threads"], a["portable"]), []).append(a)
    rows = []
    for group in groups.values():
        env = {k: v for k, v in os.environ.items()
               if k not in portable.TORCH_ENV and k != portable.ENV_VAR}
        if group[0]["portable"]:  # what `usplat` sets before torch loads
            env.update({portable.ENV_VAR: "1", **portable.TORCH_ENV})
        cmd = [sys.executable, __file__, "_throughput", "--data", args.data, "--steps",
               str(args.steps), "--arms", *[a["name"] for a in group]]
        out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env).stdout
        rows += [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    base = next((r for r in rows if r["arm"] == args.arms[0]), rows[0])
    for machine in dict.fromkeys(r["machine"] for r in rows):  # one per measuring process
        print(machine)
    print(f"{'arm':<12} {'wall ms':>8} {'CPU ms':>8} {'ex/CPU-s':>9} {'ex/wall-s':>10} "
          f"{'x ' + base['arm']:>8}")
    for r in rows:
        print(f"{r['arm']:<12} {r['wall_ms']:8.1f} {r['cpu_ms']:8.1f} "
              f"{r['examples_per_cpu_s']:9.2f} {r['examples_per_wall_s']:10.2f} "
              f"{r['examples_per_cpu_s'] / base['examples_per_cpu_s']:8.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


def _throughput(args) -> None:
    from usplat_dr.config import load_config
    from usplat_dr.evaluation.timing import interleaved, machine_line
    from usplat_dr.training import Trainer

    arms = [parse_arm(a) for a in args.arms]
    steps = {}
    for a in arms:
        torch.manual_seed(0)
        tr = Trainer(load_config([RECIPE], overrides(
            a, args.data, f"/tmp/epc_throughput/{a['name']}", 10**6, 0) + [
            "train.progress=false"]))
        # each arm's batches, read before the timing (the loop does not time data loading)
        batches = iter([tr.batches.next() for _ in range(args.steps + 3)])
        steps[a["name"]] = partial(train_step, tr, batches)
    # 3 warm-up steps; then the arms interleaved step by step, in reverse order every other step
    times = interleaved(steps, args.steps, warmup=3)
    machine = machine_line()
    for a in arms:
        t = times[a["name"]]  # ms
        print(json.dumps({"arm": a["name"], "threads": a["threads"], "batch": a["batch"],
                          "wall_ms": t.wall, "cpu_ms": t.cpu,
                          "examples_per_cpu_s": a["batch"] / (t.cpu / 1e3),
                          "examples_per_wall_s": a["batch"] / (t.wall / 1e3),
                          "machine": machine}))


def train_step(trainer, batches) -> None:
    """One optimiser step of ``trainer`` on the next of ``batches``."""
    trainer.train_step(next(batches))
    trainer.step += 1


def train_arm(args) -> None:
    """Train one arm; every checkpoint is also kept as ``checkpoints/step_<N>.ckpt``."""
    from usplat_dr.config import load_config
    from usplat_dr.training import Trainer

    arm = parse_arm(args.arm)
    out = Path(args.out) / f"{arm['name']}_seed{args.seed}"
    trainer = Trainer(load_config([RECIPE], overrides(arm, args.data, str(out), args.steps,
                                                      args.seed)))
    save = trainer.save

    def save_and_keep():
        path = save()
        if path is not None:
            kept = path.parent / f"step_{trainer.step:06d}.ckpt"
            shutil.copyfile(path, kept.with_suffix(".tmp"))
            kept.with_suffix(".tmp").replace(kept)
        return path

    trainer.save = save_and_keep
    (out / "arm.json").parent.mkdir(parents=True, exist_ok=True)
    (out / "arm.json").write_text(json.dumps({**arm, "steps": args.steps, "seed": args.seed,
                                              "data": args.data}))
    with trainer.hold_folder():
        trainer.resume()
        trainer.fit()


def cpu_at_steps(run: Path) -> dict[int, float]:
    """Process CPU seconds of ``run`` at each logged step of its metrics.csv (``cpu_s``:
    counted across resumes by the run log)."""
    with open(run / "metrics.csv", newline="") as f:
        return {int(r["step"]): float(r["cpu_s"]) for r in csv.DictReader(f) if r.get("cpu_s")}


def cpu_at(logged: dict[int, float], step: int) -> float | None:
    """CPU seconds at ``step``, linear between the logged steps around it (a checkpoint step
    need not be a logging step); None outside them.

    Examples:
        >>> cpu_at({10: 2.0, 20: 4.0}, 15), cpu_at({10: 2.0, 20: 4.0}, 20), cpu_at({10: 2.0}, 5)
        (3.0, 4.0, None)
    """
    if step in logged:
        return logged[step]
    below = [s for s in logged if s < step]
    above = [s for s in logged if s > step]
    if not below or not above:
        return None
    a, b = max(below), min(above)
    return logged[a] + (logged[b] - logged[a]) * (step - a) / (b - a)


def chart(args) -> None:
    """Each run's kept checkpoints on the held-out split, with the run's CPU time at their
    step: ``points.csv``, a chart ``psnr_per_cpu_hour.png`` and the table on stdout."""
    from usplat_dr.evaluation import evaluate, synthetic_indices
    from usplat_dr.training.checkpoints import load_model
    from usplat_dr.training.distributed import set_threads

    set_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    indices = synthetic_indices(args.eval_data, [args.split])
    points_file = out / "points.csv"
    done = {}
    if points_file.is_file():  # a rerun evaluates only new checkpoints
        with open(points_file, newline="") as f:
            done = {(r["run"], int(r["step"])): r for r in csv.DictReader(f)}
    points = []
    for run in sorted(p for p in Path(args.runs).iterdir() if (p / "arm.json").is_file()):
        arm = json.loads((run / "arm.json").read_text())
        cpu = cpu_at_steps(run)
        for ckpt in sorted((run / "checkpoints").glob("step_*.ckpt")):
            step = int(ckpt.stem.split("_")[1])
            if (run.name, step) in done:
                points.append({**done[(run.name, step)], "cpu_s": cpu_at(cpu, step) or ""})
                continue
            model, _ = load_model(ckpt)
            dataset = {"name": "synth", "roots": [args.eval_data], "image_shape": [64, 64]}
            summary = evaluate(model, dataset, indices, out / "eval" / run.name / str(step),
                               label=f"{run.name} step {step}", images_per_split=0,
                               progress=False)
            psnr = summary["splits"][args.split]["psnr"]
            points.append({"run": run.name, "arm": arm["name"], "step": step,
                           "examples": step * arm["batch"], "cpu_s": cpu_at(cpu, step) or "",
                           "psnr": psnr})
            print(json.dumps(points[-1]), flush=True)
    fields = ["run", "arm", "step", "examples", "cpu_s", "psnr"]
    tmp = points_file.with_suffix(".tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(points)
    tmp.replace(points_file)
    table(points, args.baseline)
    plot(points, out / "psnr_per_cpu_hour.png")


def table(points: list[dict], baseline: str | None) -> None:
    """Last point of each run: CPU hours, examples per CPU-second, PSNR (and vs baseline)."""
    last = {}
    for p in points:
        if p["cpu_s"] != "" and (p["run"] not in last or int(p["step"]) > int(last[p["run"]]
                                                                          ["step"])):
            last[p["run"]] = p
    base = next((p for r, p in last.items() if r.startswith(f"{baseline}_")), None)
    print(f"{'run':<20} {'steps':>6} {'CPU h':>6} {'ex/CPU-s':>9} {'PSNR':>7} {'vs base':>8}")
    for run, p in sorted(last.items()):
        rate = int(p["examples"]) / float(p["cpu_s"])
        rel = (f"{rate / (int(base['examples']) / float(base['cpu_s'])):.2f}x "
               f"{float(p['psnr']) - float(base['psnr']):+.2f} dB" if base else "")
        print(f"{run:<20} {int(p['step']):6d} {float(p['cpu_s']) / 3600:6.3f} {rate:9.2f} "
              f"{float(p['psnr']):7.2f} {rel}")


def plot(points: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 4.4))
    for run in sorted({p["run"] for p in points}):
        mine = [p for p in points if p["run"] == run and p["cpu_s"] != ""]
        if not mine:
            continue
        ps = sorted((float(p["cpu_s"]) / 3600, float(p["psnr"]), int(p["examples"]))
                    for p in mine)
        arm = parse_arm(mine[0]["arm"])
        rate = ps[-1][2] / (ps[-1][0] * 3600)
        label = (f"{run}: {arm['threads']} thread(s), {arm['batch']} scene(s)/step, "
                 f"{rate:.2f} ex/CPU-s")
        ax.plot([x for x, _, _ in ps], [y for _, y, _ in ps], "o--" if arm["threads"] > 1
                else "o-", label=label)
    ax.set_xlabel("process CPU hours (all threads)")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title("tiny (a) from scratch: held-out PSNR against CPU time")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp, dpi=120)
    tmp.replace(path)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    t = sub.add_parser("throughput", help="examples per CPU-second of each arm")
    t.add_argument("--data", required=True, help="a synthetic training set (64x64)")
    t.add_argument("--arms", nargs="+", default=["t2b1", "t1b1", "t1b2", "t1b4"],
                   help="the first is the baseline of the ratios")
    t.add_argument("--steps", type=int, default=12, help="timed steps per arm")
    t.add_argument("--json", help="also write the rows here")
    h = sub.add_parser("_throughput")  # one thread count's arms (run by throughput)
    h.add_argument("--data", required=True)
    h.add_argument("--arms", nargs="+", required=True)
    h.add_argument("--steps", type=int, required=True)
    r = sub.add_parser("train", help="train one arm from scratch, keeping its checkpoints")
    r.add_argument("--data", required=True)
    r.add_argument("--arm", required=True)
    r.add_argument("--steps", type=int, required=True, help="its optimiser steps")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--out", required=True, help="runs go in OUT/<arm>_seed<seed>")
    c = sub.add_parser("chart", help="held-out PSNR of the kept checkpoints against CPU time")
    c.add_argument("--runs", required=True, help="the --out of train")
    c.add_argument("--eval-data", required=True, help="a held-out synthetic set")
    c.add_argument("--split", default="standard")
    c.add_argument("--baseline", default="t2b1", help="the arm the table compares against")
    c.add_argument("--out", required=True)
    c.add_argument("--threads", type=int, default=1, help="threads for the evaluations")
    args = p.parse_args(argv)
    {"throughput": throughput, "_throughput": _throughput, "train": train_arm,
     "chart": chart}[args.command](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
