"""Does the automatic count follow content? Per held-out scene, the fraction of the Gaussians
``usplat eval --gaussians auto`` rendered against the share of the scene's context pixels that
are textured (the synthetic scenes know each pixel's material), by scene kind
(train/studies/LOG.md, "An automatic count").

    python train/studies/auto_content.py --eval outputs/auto_eval/auto2 \\
        --data outputs/big/test5000 --out docs/auto_keep_content.png

Prints the points' Spearman rank correlation per kind and over all scenes, and writes the
scatter chart.
"""

import argparse
import csv
import statistics
from pathlib import Path

import torch

import usplat_dr  # noqa: F401  (libLLVM first)
from usplat_dr.data.synth.render import TEXTURED
from usplat_dr.evaluation import held_out_scenes, load_example
from usplat_dr.io import save_figure


def spearman(xs: list[float], ys: list[float]) -> float:
    """Spearman's rank correlation (average ranks for ties; NaN for fewer than 3 points or a
    constant side).

    Examples:
        >>> spearman([1, 2, 3, 4], [10, 20, 30, 40]), spearman([1, 2, 3], [3, 2, 1])
        (1.0, -1.0)
    """
    def ranks(v):
        order = sorted(range(len(v)), key=lambda i: v[i])
        r = [0.0] * len(v)
        i = 0
        while i < len(v):
            j = i
            while j + 1 < len(v) and v[order[j + 1]] == v[order[i]]:
                j += 1
            for k in range(i, j + 1):
                r[order[k]] = (i + j) / 2 + 1
            i = j + 1
        return r
    if len(xs) < 3:
        return float("nan")
    rx, ry = ranks(xs), ranks(ys)
    sx, sy = statistics.pstdev(rx), statistics.pstdev(ry)
    if sx == 0 or sy == 0:
        return float("nan")
    mx, my = statistics.mean(rx), statistics.mean(ry)
    return sum((a - mx) * (b - my) for a, b in zip(rx, ry)) / (len(rx) * sx * sy)


def textured_share(material: torch.Tensor) -> float:
    """The share of the context pixels whose material is textured (codes of
    ``data.synth.render``)."""
    return float((material.round() == TEXTURED).float().mean())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--eval", type=Path, required=True,
                   help="a usplat eval --gaussians auto folder (its per_scene.csv)")
    p.add_argument("--data", required=True, help="the synthetic set it evaluated")
    p.add_argument("--size", type=int, default=64, help="the evaluation's image size")
    p.add_argument("--out", type=Path, default=Path("docs/auto_keep_content.png"))
    args = p.parse_args(argv)
    with open(args.eval / "per_scene.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["split"] == "standard"]
    if not rows or "auto_keep" not in rows[0]:
        p.error(f"--eval {args.eval}: no standard-split rows of usplat eval --gaussians auto")
    dataset, index, _ = held_out_scenes(args.data, size=args.size)
    points = []
    for r in rows:
        batch = load_example(dataset, index, r["scene"])
        material = batch["context"].get("material")
        if material is None:
            p.error(f"--data {args.data}: scene {r['scene']} has no material maps")
        rendered = float(r["gaussians_rendered"]) / float(r["gaussians_total"])
        points.append((r["scene"].split("_")[0], textured_share(material[0]), rendered,
                       float(r["auto_keep"])))
    kinds = sorted({k for k, *_ in points})
    print("| kind | scenes | textured share | rendered | chosen | Spearman (textured, rendered) |")
    print("|---|---|---|---|---|---|")
    for kind in [*kinds, "all"]:
        mine = [pt for pt in points if kind in ("all", pt[0])]
        rho = spearman([pt[1] for pt in mine], [pt[2] for pt in mine])
        print(f"| {kind} | {len(mine)} | {statistics.mean(pt[1] for pt in mine):.2f} | "
              f"{statistics.mean(pt[2] for pt in mine):.1%} | "
              f"{statistics.mean(pt[3] for pt in mine):.1%} | {rho:+.2f} |")
    import matplotlib  # only here: the chart

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.2))
    for kind in kinds:
        mine = [pt for pt in points if pt[0] == kind]
        ax.scatter([pt[1] for pt in mine], [pt[2] for pt in mine], label=kind, s=22)
    ax.set_xlabel("share of the context pixels that are textured")
    ax.set_ylabel("Gaussians rendered (culled, merged, counted)")
    ax.set_title("--gaussians auto per held-out scene (64x64, seed 5000)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    print(f"wrote {save_figure(fig, args.out)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
