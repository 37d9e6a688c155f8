"""Training steps with the cores kept awake (``usplat_dr.training.cores.CoreKeeper``, what ``usplat
train`` does with ``keep_cores_awake=true``, and by default where its threads cover every core and
its start-up probe finds idle cores slow to wake) against without: each setting in
its own processes, alternated round by round (a busy host slows both alike), the spinners
running for the whole process as in a training run. Per process (``training.py --awake on|off``
beside this script, run as a subprocess): the median of ``--steps`` timed steps (after 3 warm-up
steps) of the tiny preset at 64x64, 2 context + 4 targets, the shipped recipe, phase by phase
as ``training.py`` times them; then the median over rounds. Wall and process CPU time (the
spinners' CPU time is not counted: it is time the job left idle).

    python train/bench/cores.py --data outputs/big/train480 --threads 2 --rounds 4
"""

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

#: The script that times one process's steps (a subprocess per round and setting).
TRAINING = Path(__file__).resolve().with_name("training.py")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="a synthetic training set (64x64)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--steps", type=int, default=15, help="timed steps per process")
    p.add_argument("--rounds", type=int, default=4)
    p.add_argument("--variants", nargs="+", default=["baseline", "full"])
    args = p.parse_args(argv)
    runs = {"off": [], "on": []}
    for r in range(args.rounds):
        for setting, results in runs.items():
            cmd = [sys.executable, str(TRAINING), "--data", args.data,
                   "--threads", str(args.threads), "--steps", str(args.steps), "--variants",
                   *args.variants, "--awake", setting]
            res = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if res.returncode:
                sys.exit(f"round {r + 1}, cores awake {setting}: failed\n{res.stderr[-2000:]}")
            results.append(json.loads(res.stdout.strip().splitlines()[-1]))
            totals = ", ".join(f"{v} {results[-1][v]['wall']['total']:.1f} ms"
                               for v in args.variants)
            print(f"round {r + 1}/{args.rounds}, cores awake {setting}: {totals}", flush=True)
    if runs["on"][0]["spinners"] == 0:
        print("note: no spinner started here (not Linux, or SCHED_IDLE refused): both rows "
              "ran without")
    phases = list(runs["on"][0][args.variants[0]]["wall"])  # training.py's, in its order
    print(f"\nthreads={args.threads}, {args.rounds} rounds x {args.steps} steps per process; "
          f"medians over rounds of per-process medians (ms); CPU = process CPU time")
    print("| variant | cores | " + " | ".join(phases) + " | steps/s | CPU ms/step |")
    print("|---|---|" + "---|" * (len(phases) + 2))
    for variant in args.variants:
        for setting, label in (("off", "idle halts"), ("on", "kept awake")):
            med = {ph: statistics.median(x[variant]["wall"][ph] for x in runs[setting])
                   for ph in phases}
            cpu = statistics.median(x[variant]["cpu"] for x in runs[setting])
            print(f"| {variant} | {label} | " + " | ".join(f"{med[ph]:.1f}" for ph in phases)
                  + f" | {1000 / med['total']:.2f} | {cpu:.0f} |")
    for variant in args.variants:
        on, off = (statistics.median(x[variant]["wall"]["total"] for x in runs[s])
                   for s in ("on", "off"))
        per_round = " ".join(f"{a[variant]['wall']['total'] / b[variant]['wall']['total']:.2f}"
                             for a, b in zip(runs["on"], runs["off"]))
        print(f"{variant}: kept awake / idle halts = {on / off:.3f} (per round: {per_round})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
