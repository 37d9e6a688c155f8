"""How long torch's OpenMP threads spin after a parallel region (``GOMP_SPINCOUNT``), against
training throughput and the rasteriser at 2 threads (a script, not a test).

torch's CPU wheels use GNU OpenMP: after each parallel operation its worker threads keep
spinning on their core (300,000 iterations by default, milliseconds) before they sleep. Dr.Jit
runs its kernels on its own thread pool, so right after a torch operation its threads share
the cores with spinning torch workers. The setting is read once per process, when libgomp
loads, so each value runs in its own processes, alternated round by round (a busy machine
hits all alike): ``train/bench/training.py`` (the current trainer, tiny preset, 64x64,
2 context + 4 targets) and ``train/bench/rasterizer.py`` (torch entry, pixel-aligned scenes).
Prints medians over rounds and ratios against the first value (``default``: the variable
unset, libgomp's own default, as before this script).

    python train/bench/omp_spin.py --data outputs/big/train480 --rounds 3
"""

import argparse
import os
import re
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def run(script: str, args: list[str], spin: str) -> str:
    env = dict(os.environ)
    env.pop("GOMP_SPINCOUNT", None)
    env.pop("OMP_WAIT_POLICY", None)
    # usplat_dr sets GOMP_SPINCOUNT from this on import, before torch (usplat_dr/_threads.py)
    env["USPLAT_OMP_SPIN"] = "off" if spin == "default" else spin
    out = subprocess.run([sys.executable, str(HERE / script), *args], env=env,
                         capture_output=True, text=True, check=True)
    return out.stdout


def parse_training(text: str) -> dict:
    """ms per step of the current trainer, per variant."""
    found = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) > 8 and cells[1] == "current":
            found[f"train {cells[0]} ms/step"] = float(cells[8])
    return found


def parse_raster(text: str) -> dict:
    found = {}
    for line in text.splitlines():
        m = re.match(r"\| (\d+)x\d+ \| [\d,]+ \| [\d,]+ \| ([\d.]+) \([\d.]+\) \| ([\d.]+) ", line)
        if m:
            found[f"raster {m[1]} fwd ms"] = float(m[2])
            found[f"raster {m[1]} fwd+bwd ms"] = float(m[3])
    return found


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="a synthetic training set (64x64)")
    p.add_argument("--values", nargs="+", default=["default", "30000", "10000"],
                   help="GOMP_SPINCOUNT values ('default': unset); the first is the baseline")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    samples: dict = {v: {} for v in args.values}
    for r in range(args.rounds):
        for v in args.values:
            got = parse_training(run("training.py", [
                "--data", args.data, "--threads", str(args.threads), "--steps", "10"], v))
            got |= parse_raster(run("rasterizer.py", [
                "--sizes", "64", "256", "--runs", "9", "--threads", str(args.threads)], v))
            for k, x in got.items():
                samples[v].setdefault(k, []).append(x)
            print(f"round {r + 1}, GOMP_SPINCOUNT={v}: " + ", ".join(
                f"{k} {x:.1f}" for k, x in got.items()), flush=True)
    base = args.values[0]
    keys = list(samples[base])
    print(f"\nmedians over {args.rounds} rounds, {args.threads} threads; ratio to "
          f"GOMP_SPINCOUNT={base}\n")
    print("| GOMP_SPINCOUNT | " + " | ".join(keys) + " |")
    print("|---|" + "---|" * len(keys))
    for v in args.values:
        cells = []
        for k in keys:
            m = statistics.median(samples[v][k])
            cells.append(f"{m:.1f} ({m / statistics.median(samples[base][k]):.2f}x)")
        print(f"| {v} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
