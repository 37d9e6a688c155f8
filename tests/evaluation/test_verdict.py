"""The verdict's statistics: the bootstrap interval against the normal-theory interval it
must approach, seed variation widening it, and paired comparisons of per-scene CSVs."""

import csv

import numpy as np
import pytest

from usplat_dr.evaluation.verdict import bootstrap_interval, chart, compare, table


def test_bootstrap_interval_approaches_the_normal_interval():
    rng = np.random.default_rng(1)
    d = rng.normal(0.3, 1.0, size=(1, 400))
    lo, hi = bootstrap_interval(d, samples=20_000)
    m, se = d.mean(), d.std(ddof=1) / np.sqrt(d.size)
    # The percentile bootstrap of a mean of 400 normal values matches mean +- 1.96 se up to
    # its Monte Carlo error (~1% of the width at 20k samples) and the n vs n-1 factor.
    assert lo == pytest.approx(m - 1.96 * se, abs=0.05 * se * 3.92)
    assert hi == pytest.approx(m + 1.96 * se, abs=0.05 * se * 3.92)


def test_seed_variation_widens_the_interval():
    rng = np.random.default_rng(2)
    scenes = rng.normal(0, 0.2, size=(1, 60))
    # three seeds that disagree by +-1 dB: the scene-only interval would be ~0.1 wide
    d = scenes + np.array([[-1.0], [0.0], [1.0]])
    lo, hi = bootstrap_interval(d, samples=5000)
    lo1, hi1 = bootstrap_interval(d[1:2], samples=5000)
    assert hi - lo > 5 * (hi1 - lo1)
    assert lo < 0 < hi


def test_nan_entries_are_left_out_and_bad_shapes_refused():
    d = np.array([[1.0, np.nan, 1.0]])
    assert bootstrap_interval(d, samples=100) == (1.0, 1.0)
    with pytest.raises(ValueError, match="seeds, scenes"):
        bootstrap_interval(np.zeros(5))


def _write(path, rows):
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["split", "scene", "targets", "psnr", "ssim",
                                          "lpips", "abs_rel", "rmse", "delta1"])
        w.writeheader()
        w.writerows(rows)
    return path


def test_compare_pairs_scenes_and_seeds(tmp_path):
    rng = np.random.default_rng(3)
    runs = {"baseline": [], "full": []}
    for s in range(3):
        base = [{"split": sp, "scene": f"k{k}", "targets": 3,
                 "psnr": 20 + rng.normal(0, 3), "ssim": 0.6, "abs_rel": 0.2}
                for sp in ("standard", "glossy") for k in range(50)]
        full = [{**r, "psnr": r["psnr"] + (0.5 if r["split"] == "standard" else -0.2),
                 "abs_rel": r["abs_rel"] - 0.01} for r in base]
        full.append({**full[0], "scene": "only_in_full"})  # not paired: ignored
        runs["baseline"].append(_write(tmp_path / f"a{s}.csv", base))
        runs["full"].append(_write(tmp_path / f"c{s}.csv", full))
    rows = compare(runs, samples=500)
    by = {(r.split, r.metric): r for r in rows}
    std = by[("standard", "psnr")]
    # the scene-to-scene spread (3 dB) cancels in the pairing: the difference is exact
    assert std.mean == pytest.approx(0.5) and std.low == pytest.approx(0.5)
    assert std.scenes == 50 and std.seeds == 3 and std.verdict == "better"
    assert by[("glossy", "psnr")].verdict == "worse"
    assert by[("standard", "abs_rel")].verdict == "better"  # lower is better
    assert by[("standard", "ssim")].verdict == "no difference shown"
    assert [r.split for r in rows][0] == "standard"
    assert "(c) - (a)" in table(rows)
    assert chart(rows, tmp_path / "verdict.png").stat().st_size > 0
    with pytest.raises(ValueError, match="same number of seeds"):
        compare({"baseline": runs["baseline"], "full": runs["full"][:2]})
