"""The oracle's convergence check: per-target minus shared (dB, per scene the mean over its
targets) at two step counts of ``oracle_delta.py`` on the same scenes, how far it moved, and
the t interval over the scenes (two-sided 95%).

    python train/studies/oracle_convergence.py \\
        --before 'outputs/oracle/all_r4_s1000*/per_target.csv' \\
        --after 'outputs/oracle/all_r4_s3000_*/per_target.csv'
"""

import argparse
import csv
import glob
import math
import statistics

from scipy import stats


def per_scene(pattern: str) -> dict[str, float]:
    """``{scene: mean over its targets of per_target - shared}`` from the matching CSVs."""
    rows: dict[str, list[float]] = {}
    for path in sorted(glob.glob(pattern)):
        with open(path) as f:
            for r in csv.DictReader(f):
                rows.setdefault(r["scene"], []).append(float(r["per_target"]) - float(r["shared"]))
    if not rows:
        raise SystemExit(f"no oracle_delta.py per_target.csv matches {pattern!r}")
    return {k: statistics.mean(v) for k, v in rows.items()}


def interval(values: list[float]) -> tuple[float, float, float]:
    """Mean and two-sided 95% t interval."""
    m, n = statistics.mean(values), len(values)
    half = stats.t.ppf(0.975, n - 1) * statistics.stdev(values) / math.sqrt(n)
    return m, m - half, m + half


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--before", required=True, help="glob of the fewer-steps per_target.csv")
    p.add_argument("--after", required=True, help="glob of the more-steps per_target.csv")
    args = p.parse_args(argv)
    before, after = per_scene(args.before), per_scene(args.after)
    scenes = sorted(set(before) & set(after))
    if len(scenes) < 2:
        raise SystemExit(f"{len(scenes)} scene(s) in both: need 2 or more")
    for k in scenes:
        print(f"{k}: {before[k]:+.3f} -> {after[k]:+.3f} dB ({after[k] - before[k]:+.3f})")
    for name, values in (("before", [before[k] for k in scenes]),
                         ("after", [after[k] for k in scenes]),
                         ("moved", [after[k] - before[k] for k in scenes])):
        m, lo, hi = interval(values)
        print(f"{name}: {m:+.3f} dB [{lo:+.3f}, {hi:+.3f}] over {len(scenes)} scenes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
