"""The Gaussian budget at two image sizes: do denser pixels leave more to drop?
(train/studies/LOG.md, "The learned budget at 128x128", its rule fixed before its runs.)

    python train/studies/budget_sizes.py --small outputs/budget128/64_{learned,dither} \\
        --large outputs/budget128/128_{learned,dither} --out docs/budget_chart_128.png

Each folder is an ``auto_budget_proxy.py --out`` of one model and ranking on the held-out
scenes at one size (``proxy.csv``: per scene and fraction kept, the loss against the model's
render with every Gaussian); the ranking is read from each folder's ``summary.json``. Scenes
are paired by name (the same seed-5000 scenes at both sizes). Prints, per ranking and fraction,
the mean loss at each size and the paired difference (large minus small) with its 95% t
interval over scenes; the rule at ``--rule-keep`` with the ``--rule-ranking`` ranking; and
draws loss against the fraction kept. Writes the numbers to ``OUT`` with a ``.json`` suffix.
"""

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

from usplat_dr.evaluation.verdict import t_interval
from usplat_dr.io import save_figure, write_json


def losses(folder: Path) -> dict[float, dict[str, float]]:
    """{fraction kept (< 1): {scene: loss in dB}} of an ``auto_budget_proxy.py`` folder."""
    found: dict[float, dict[str, float]] = {}
    with open(folder / "proxy.csv", newline="") as f:
        for row in csv.DictReader(f):
            if float(row["keep"]) < 1.0:
                found.setdefault(float(row["keep"]), {})[row["scene"]] = float(row["real_loss"])
    if not found:
        raise ValueError(f"{folder / 'proxy.csv'} has no row with a fraction below 1")
    return dict(sorted(found.items()))


def ranking(folder: Path) -> str:
    """The ranking an ``auto_budget_proxy.py`` folder was measured with."""
    summary = json.loads((folder / "summary.json").read_text())
    return summary["rank_by"]


def label(low: float, high: float) -> str:
    """The registered rule on (large - small) loss: negative means the large size loses less."""
    if high < 0:
        return "denser pixels leave more to drop"
    if low > 0:
        return "denser pixels leave less to drop"
    return "no difference shown"


def compare(small: dict, large: dict) -> dict[float, dict]:
    """Per fraction both have: the mean loss at each size over the scenes both have, and the
    paired difference (large - small) with its 95% t interval."""
    rows = {}
    for keep in sorted(set(small) & set(large)):
        scenes = sorted(set(small[keep]) & set(large[keep]))
        if len(scenes) < 2:
            raise ValueError(f"at {keep:g} the two sizes share {len(scenes)} scene(s): need 2 "
                             "or more (the same held-out seed at both sizes)")
        a = np.array([small[keep][s] for s in scenes])
        b = np.array([large[keep][s] for s in scenes])
        low, high = t_interval(b - a)
        rows[keep] = {"scenes": len(scenes), "small": float(a.mean()), "large": float(b.mean()),
                      "difference": float((b - a).mean()), "low": low, "high": high,
                      "label": label(low, high),
                      "unpaired": len(set(small[keep]) ^ set(large[keep]))}
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--small", type=Path, nargs="+", required=True,
                   help="auto_budget_proxy.py folders at the small size, one per ranking")
    p.add_argument("--large", type=Path, nargs="+", required=True,
                   help="the same rankings at the large size")
    p.add_argument("--sizes", type=int, nargs=2, default=(64, 128), metavar=("SMALL", "LARGE"))
    p.add_argument("--rule-keep", type=float, default=0.3)
    p.add_argument("--rule-ranking", default="learned")
    p.add_argument("--out", type=Path, required=True, help="the chart (PNG)")
    args = p.parse_args(argv)
    small, large = {}, {}
    for where, folders in ((small, args.small), (large, args.large)):
        for f in folders:
            r = ranking(f)
            if r in where:
                p.error(f"two folders of one size measured {r}: {f} and another; give one "
                        "folder per ranking and size")
            where[r] = losses(f)
    if set(small) != set(large):
        p.error(f"--small has the rankings {sorted(small)}, --large {sorted(large)}: give the "
                "same ones at both sizes")
    if args.rule_ranking not in small:
        p.error(f"--rule-ranking {args.rule_ranking} is not among {sorted(small)}")
    lo, hi = args.sizes
    result = {r: compare(small[r], large[r]) for r in sorted(small)}
    for r, rows in result.items():
        print(f"{r}: kept | {lo}x{lo} | {hi}x{hi} | {hi} - {lo} [95% t]")
        for keep, row in rows.items():
            print(f"  {keep:.0%} | {row['small']:+.2f} | {row['large']:+.2f} | "
                  f"{row['difference']:+.2f} [{row['low']:+.2f}, {row['high']:+.2f}] "
                  f"({row['scenes']} scenes)")
    dropped = {r: max(row["unpaired"] for row in rows.values()) for r, rows in result.items()}
    for r, n in dropped.items():
        if n:
            print(f"{r}: {n} scene(s) measured at one size only, left out of the pairs")
    ruled = result[args.rule_ranking].get(args.rule_keep)
    if ruled is None:
        p.error(f"--rule-keep {args.rule_keep} is not a fraction both sizes measured")
    print(f"rule ({args.rule_ranking} at {args.rule_keep:.0%}): {ruled['label']} "
          f"({ruled['difference']:+.3f} [{ruled['low']:+.3f}, {ruled['high']:+.3f}] dB)")

    import matplotlib  # only here: the chart

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for i, (r, rows) in enumerate(result.items()):
        keeps = list(rows)
        for size, key, style in ((lo, "small", "--"), (hi, "large", "-")):
            ax.plot(keeps, [rows[k][key] for k in keeps], style, marker="os"[i % 2], ms=4,
                    color=f"C{i}", label=f"{r}, {size}x{size}")
    ax.axhline(0, color="grey", lw=0.6)
    ax.set_xlabel("fraction of the model's Gaussians kept per target")
    ax.set_ylabel("PSNR loss against all Gaussians, dB")
    ax.set_title(f"The Gaussian budget at {lo}x{lo} and {hi}x{hi} (held out, standard split)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    print(f"wrote {save_figure(fig, args.out)}")
    write_json(args.out.with_suffix(".json"),
               {"sizes": [lo, hi], "rule": {"ranking": args.rule_ranking,
                                            "keep": args.rule_keep, **ruled},
                "rankings": {r: {f"{k:g}": row for k, row in rows.items()}
                             for r, rows in result.items()}})
    return 0


if __name__ == "__main__":
    sys.exit(main())
