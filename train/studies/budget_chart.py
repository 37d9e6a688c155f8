"""The Gaussian budget's chart: what keeping a fraction of the Gaussians costs on the held-out
set, per ranking, beside the bound (what that many Gaussians reach when free to move), the
merge-then-drop rule and the automatic count (train/studies/LOG.md, "The bound of a Gaussian
budget" and "An automatic count").

    python train/studies/budget_chart.py --out docs/budget_chart.png \\
        [--eval-all outputs/auto_eval/all --eval-auto outputs/auto_eval/auto]

Reads the committed measurements in train/studies/auto_budget/: per-scene losses of the dither
ranking (``heldout_proxy.csv``, tiny_full) and the learned one (``learned_heldout_proxy.csv``,
tiny_full_budget), the automatic count's choices (``*heldout_summary.json``, calibrated, at
tolerances 0.2, 0.5 and 1 dB), the bound and the merge (``bound_and_merge.json``); with
``--eval-all``/``--eval-auto`` (two ``usplat eval`` folders on the same scenes, without a
budget and with ``--gaussians auto``), the count as built (merging included) from their
``per_scene.csv``. Prints the points it draws.
"""

import argparse
import csv
import json
import statistics
from pathlib import Path

HERE = Path(__file__).parent / "auto_budget"


def mean_losses(path: Path) -> dict[float, float]:
    """{keep: the mean over scenes of the real (target) loss} of a study's ``proxy.csv``."""
    found: dict[float, list[float]] = {}
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            if float(row["keep"]) < 1.0:
                found.setdefault(float(row["keep"]), []).append(float(row["real_loss"]))
    return {k: statistics.mean(v) for k, v in sorted(found.items())}


def auto_points(path: Path, tolerances=("0.2", "0.5", "1.0")) -> list[tuple[str, float, float]]:
    """(tolerance, mean kept, mean loss) of the calibrated count in a study's summary."""
    rows = json.loads(path.read_text())["rows"]["calibrated"]
    return [(t, rows[t]["mean_kept"], rows[t]["mean_loss_db"]) for t in tolerances if t in rows]


def eval_point(all_dir: Path, auto_dir: Path) -> tuple[float, float, float, int]:
    """(mean kept fraction rendered, mean loss, worst scene's loss, scenes) of ``usplat eval
    --gaussians auto`` against the same evaluation without a budget, matched by scene."""
    def rows(d):
        with open(d / "per_scene.csv", newline="") as f:
            return {(r["split"], r["scene"]): r for r in csv.DictReader(f)}
    a, b = rows(all_dir), rows(auto_dir)
    common = sorted(set(a) & set(b))
    if not common:
        raise ValueError(f"{all_dir} and {auto_dir} share no scene")
    loss = [float(a[k]["psnr"]) - float(b[k]["psnr"]) for k in common]
    kept = [float(b[k]["gaussians_rendered"]) / float(b[k]["gaussians_total"]) for k in common]
    return statistics.mean(kept), statistics.mean(loss), max(loss), len(common)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=Path("docs/budget_chart.png"))
    p.add_argument("--eval-all", type=Path, help="usplat eval folder without a budget")
    p.add_argument("--eval-auto", type=Path, help="the same with --gaussians auto")
    args = p.parse_args(argv)
    if (args.eval_all is None) != (args.eval_auto is None):
        p.error("give both --eval-all and --eval-auto, or neither")
    import matplotlib  # only here: the chart

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from usplat_dr.io import save_figure

    other = json.loads((HERE / "bound_and_merge.json").read_text())
    lines = {
        "dither (tiny_full)": mean_losses(HERE / "heldout_proxy.csv"),
        "learned (tiny_full_budget)": mean_losses(HERE / "learned_heldout_proxy.csv"),
        "merge, then dither": dict(zip(other["merge_then_dither"]["keep"],
                                       other["merge_then_dither"]["loss_db"])),
        "bound: K Gaussians fitted": dict(zip(other["bound"]["keep"],
                                              other["bound"]["loss_db"])),
    }
    styles = {"dither (tiny_full)": "o-", "learned (tiny_full_budget)": "s-",
              "merge, then dither": "^--", "bound: K Gaussians fitted": "k:"}
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    for name, pts in lines.items():
        ax.plot(list(pts), list(pts.values()), styles[name], label=name, ms=4)
        print(name, " ".join(f"{k:g}: {v:+.2f}" for k, v in pts.items()))
    for path, marker, name in ((HERE / "heldout_summary.json", "*", "auto, dither"),
                               (HERE / "learned_heldout_summary.json", "P", "auto, learned")):
        pts = auto_points(path)
        ax.scatter([k for _, k, _ in pts], [v for *_, v in pts], marker=marker, s=90,
                   zorder=3, label=f"{name} (tolerance 0.2 / 0.5 / 1 dB)")
        for tol, k, v in pts:
            print(f"{name} at {tol} dB: kept {k:.0%}, loss {v:+.2f} dB")
    if args.eval_all is not None:
        k, v, worst, n = eval_point(args.eval_all, args.eval_auto)
        ax.scatter([k], [v], marker="D", s=70, color="crimson", zorder=4,
                   label=f"--gaussians auto as built ({n} scenes, merged; worst {worst:+.2f})")
        print(f"auto as built: {n} scenes, rendered {k:.1%} of the Gaussians, mean loss "
              f"{v:+.3f} dB, worst scene {worst:+.3f} dB")
    ax.axhline(0, color="grey", lw=0.6)
    ax.set_xlabel("fraction of the model's Gaussians kept per target")
    ax.set_ylabel("PSNR loss against all Gaussians, dB")
    ax.set_ylim(-1, 10)
    ax.set_title("Held-out synthetic scenes, 64x64 (seed 5000, standard split)")
    ax.legend(fontsize=7.5)
    fig.tight_layout()
    print(f"wrote {save_figure(fig, args.out)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
