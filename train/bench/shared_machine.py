"""On a shared machine: a training step and the demo, on a quiet machine and beside one other
CPU-bound process (``python -c "while True: pass"``), with the thread count chosen from the free
cores (``USPLAT_THREADS=auto``, the default) and with one thread per allowed core whatever
else runs (``USPLAT_THREADS=all``, what ``usplat`` did before 2026-11-26).

    python train/bench/shared_machine.py --data outputs/big/train480 --steps 30
    python train/bench/shared_machine.py --data outputs/big/train480 --demo   # + the demo (long)
    python train/bench/shared_machine.py --data outputs/big/train480 --rounds 0 --demo busy:all

Each measurement runs in a fresh process (``import torch`` first, as users write), started
after the busy process has run for a second. The training step is the tiny (a) recipe's
(``synthetic_tiny_depth.yaml``, 64x64, one scene of 2 context + 4 target views a step), median
wall and process CPU time over ``--steps`` steps after 3 warm-up steps, with ``threads: null``
(the tiny configs set 1; this measures ``usplat``'s own choice); the demo is ``usplat demo``
into a fresh folder (its synthetic data included), wall time. The table gives each time over
the quiet ``auto`` one.
Results: train/bench/README.md, "On a shared machine".
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: One CPU-bound process, which asks Linux to kill it when its parent dies (prctl 1 =
#: PR_SET_PDEATHSIG), so a killed benchmark leaves no busy process behind.
BURN = ("import ctypes, signal, sys\nif sys.platform == 'linux':\n"
        "    ctypes.CDLL(None).prctl(1, signal.SIGKILL)\nwhile True: pass")


@contextmanager
def condition(name: str):
    """``busy``: one CPU-bound process for the block; ``quiet``: nothing."""
    burner = None
    if name == "busy":
        # the burner dies with this process, however it ends (Linux: PR_SET_PDEATHSIG)
        burner = subprocess.Popen([sys.executable, "-c", BURN])
        time.sleep(1.0)
    try:
        yield
    finally:
        if burner is not None:
            burner.kill()
            burner.wait()


def step_times(data: str, steps: int) -> None:
    """(Run in a child.) The recipe's step with ``threads`` unset: one JSON line."""
    import torch  # users' order

    import usplat_dr  # noqa: F401
    from usplat_dr.config import load_config
    from usplat_dr.training import Trainer

    torch.manual_seed(0)
    trainer = Trainer(load_config(["synthetic_tiny_depth.yaml"], [
        f"dataset.roots=[{data}]", "output_dir=" + tempfile.mkdtemp(prefix="shared_bench_"),
        "model.variant=baseline", "train.progress=false", "threads=null"]))
    wall, cpu = [], []
    # Own timing, not usplat_dr.evaluation.timing: one setting per process, against another's load.
    for i in range(steps + 3):
        batch = trainer.batches.next()
        w, c = time.perf_counter(), time.process_time()
        trainer.train_step(batch)
        trainer.step += 1
        if i >= 3:
            wall.append(time.perf_counter() - w)
            cpu.append(time.process_time() - c)
    print(json.dumps({"threads": torch.get_num_threads(), "wall_ms":
                      statistics.median(wall) * 1e3, "cpu_ms": statistics.median(cpu) * 1e3}))


def run_step(data: str, steps: int, setting: str) -> dict:
    env = {**os.environ, "USPLAT_THREADS": setting}
    out = subprocess.run([sys.executable, __file__, "--child-steps", str(steps), "--data", data],
                         env=env, check=True, capture_output=True, text=True, cwd=ROOT).stdout
    return json.loads(next(line for line in out.splitlines() if line.startswith("{")))


def run_demo(setting: str, budget: str, root: Path = ROOT) -> dict:
    """``usplat demo`` of the checkout ``root`` (its own ``.venv``; this one's by default)."""
    env = {**os.environ, "USPLAT_THREADS": setting}
    usplat = (root / ".venv" / "bin" / "usplat" if root != ROOT
              else Path(sys.executable).with_name("usplat"))
    with tempfile.TemporaryDirectory(prefix="shared_demo_") as out:
        t = time.perf_counter()
        args = [str(usplat), "demo", "--out", out] + (["--quick"] if budget == "quick" else [])
        subprocess.run(args, env=env, check=True, capture_output=True, cwd=root)
        return {"wall_ms": (time.perf_counter() - t) * 1e3}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="a synthetic training set (64x64)")
    p.add_argument("--steps", type=int, default=30, help="timed training steps per run")
    p.add_argument("--rounds", type=int, default=2,
                   help="rounds of (quiet, busy) step measurements; medians over rounds")
    p.add_argument("--demo", nargs="*", metavar="CONDITION:SETTING",
                   help="also time the demo (minutes each) in these conditions, e.g. "
                   "quiet:auto busy:auto busy:all (the default when given without values)")
    p.add_argument("--demo-budget", default="full", choices=["full", "quick"])
    p.add_argument("--demo-root", type=Path, default=ROOT,
                   help="the checkout whose demo runs (with its own .venv), e.g. an older "
                   "commit for a before/after")
    p.add_argument("--settings", nargs="+", default=["auto", "all"],
                   help="USPLAT_THREADS values to compare")
    p.add_argument("--child-steps", type=int, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child_steps:
        step_times(args.data, args.child_steps)
        return 0
    print(f"# {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f} at start; "
          f"{time.strftime('%Y-%m-%d %H:%M')}")
    results: dict = {}
    for _ in range(args.rounds):  # interleaved: quiet and busy alternate
        for cond in ("quiet", "busy"):
            for setting in args.settings:
                with condition(cond):
                    r = run_step(args.data, args.steps, setting)
                results.setdefault(("step", cond, setting), []).append(r)
    if args.demo is not None:
        for run in args.demo or ["quiet:auto", "busy:auto", "busy:all"]:
            cond, setting = run.split(":")
            with condition(cond):
                r = run_demo(setting, args.demo_budget, args.demo_root.resolve())
            print(f"demo {cond} {setting}: {r['wall_ms'] / 1e3:.0f} s", flush=True)
            results.setdefault(("demo", cond, setting), []).append(r)
    print("\n| what | USPLAT_THREADS | condition | threads | wall ms | CPU ms | over quiet auto |")
    print("|---|---|---|---|---:|---:|---:|")
    for what in ("step", "demo"):
        ref = results.get((what, "quiet", "auto"))
        ref_ms = statistics.median(r["wall_ms"] for r in ref) if ref else None
        for (w, cond, setting), rs in results.items():
            if w != what:
                continue
            wall = statistics.median(r["wall_ms"] for r in rs)
            cpu = (f"{statistics.median(r['cpu_ms'] for r in rs):.0f}" if "cpu_ms" in rs[0]
                   else "-")
            threads = rs[0].get("threads", "-")
            ratio = f"{wall / ref_ms:.2f}" if ref_ms else "-"
            print(f"| {what} | {setting} | {cond} | {threads} | {wall:.0f} | {cpu} | {ratio} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
