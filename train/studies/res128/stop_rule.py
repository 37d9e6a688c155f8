"""The pre-registered stopping rule of the 128x128 (a) (train/studies/LOG.md, "Four times
the pixels: models at 128x128"): the first multiple of 1,000 steps where the mean training PSNR
of the last 1,000 steps is less than ``--min-gain`` dB above the mean of the 1,000 before.

    python train/studies/res128/stop_rule.py outputs/res128_a/metrics.csv

Prints each 1,000-step window's mean PSNR and the step at which the rule stops the run (or
that it has not yet); exit code 0 when it stops, 1 when the run should go on.
"""

import argparse
import csv
import itertools
import math
import sys


def window_means(rows: list[dict], window: int) -> dict[int, float]:
    """Mean ``psnr`` of the rows in each window (k - window, k], k a multiple of ``window``,
    for the windows that are complete (some row at or after their end)."""
    last = max((int(r["step"]) for r in rows), default=0)
    means = {}
    for end in range(window, last + 1, window):
        values = [float(r["psnr"]) for r in rows
                  if end - window < int(r["step"]) <= end and r.get("psnr")
                  and math.isfinite(float(r["psnr"]))]
        if values:
            means[end] = sum(values) / len(values)
    return means


def stop_step(means: dict[int, float], min_gain: float) -> int | None:
    """The first window end whose mean is less than ``min_gain`` above the window before."""
    for before, end in itertools.pairwise(sorted(means)):
        if means[end] - means[before] < min_gain:
            return end
    return None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("metrics", help="the run's metrics.csv")
    p.add_argument("--window", type=int, default=1000, help="steps per window")
    p.add_argument("--min-gain", type=float, default=0.05, help="dB a window must gain")
    args = p.parse_args(argv)
    with open(args.metrics, newline="") as f:
        rows = list(csv.DictReader(f))
    means = window_means(rows, args.window)
    for end, value in sorted(means.items()):
        print(f"steps {end - args.window + 1}-{end}: mean training PSNR {value:.3f} dB")
    step = stop_step(means, args.min_gain)
    print(f"stop at step {step}" if step else "the rule does not stop the run yet")
    return 0 if step else 1


if __name__ == "__main__":
    sys.exit(main())
