"""The verdict's statistics: the bootstrap interval against the normal-theory interval it
must approach, seed variation widening it, and paired comparisons of per-scene CSVs."""

import csv

import numpy as np
import pytest

from usplat_dr.evaluation.verdict import (
    Comparison,
    bootstrap_interval,
    chart,
    compare,
    seed_interval,
    table,
)


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
    assert rows[0].split == "standard"
    assert "(c) - (a)" in table(rows)
    assert chart(rows, tmp_path / "verdict.png").stat().st_size > 0
    with pytest.raises(ValueError, match="same number of seeds"):
        compare({"baseline": runs["baseline"], "full": runs["full"][:2]})


def test_compare_keeps_only_the_scenes_of_the_kinds_asked(tmp_path):
    # (c) gains 1 dB on object scenes and loses 1 dB on indoor ones: over both kinds the mean
    # is 0; restricted to objects it is exactly +1 (every pair differs by exactly 1).
    base = [{"split": "standard", "scene": f"{kind}_5000_{k:05d}", "targets": 3,
             "psnr": 20.0 + k, "ssim": 0.6, "abs_rel": 0.2}
            for kind in ("indoor", "object") for k in range(10)]
    full = [{**r, "psnr": r["psnr"] + (1.0 if r["scene"].startswith("object") else -1.0)}
            for r in base]
    runs = {"baseline": [_write(tmp_path / "a.csv", base)],
            "full": [_write(tmp_path / "c.csv", full)]}
    everything = {r.metric: r for r in compare(runs, samples=200)}["psnr"]
    objects = {r.metric: r for r in compare(runs, samples=200,
                                            scene_prefixes=("object_",))}["psnr"]
    assert everything.mean == pytest.approx(0.0) and everything.scenes == 20
    assert objects.mean == pytest.approx(1.0) and objects.scenes == 10


def test_compare_takes_other_metrics_with_their_direction(tmp_path):
    # psnr_matte is not compared by default; asked for, it is read and judged higher-is-better
    # (every pair differs by exactly +0.5, so the one-seed bootstrap interval is [0.5, 0.5]).
    rows = [{"split": "standard", "scene": f"s{k}", "targets": 3, "psnr": 20.0, "ssim": 0.6,
             "abs_rel": 0.2, "psnr_matte": 20.0 + k} for k in range(20)]
    better = [{**r, "psnr_matte": r["psnr_matte"] + 0.5} for r in rows]

    def write(path, table):
        with open(path, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(table[0]))
            w.writeheader()
            w.writerows(table)
        return path

    runs = {"baseline": [write(tmp_path / "a.csv", rows)],
            "full": [write(tmp_path / "c.csv", better)]}
    assert "psnr_matte" not in {r.metric for r in compare(runs, samples=200)}
    (matte,) = compare(runs, samples=200, metrics={"psnr_matte": True})
    assert matte.mean == pytest.approx(0.5) and matte.verdict == "better (one seed)"


def test_seed_interval_is_students_t_over_the_seed_means():
    # Seed means 0.1, 0.3, 0.5 (each seed's scenes around them, one NaN left out): mean 0.3,
    # sd 0.2, t_{0.975, 2} = 4.302653 (printed tables), so 0.3 +- 4.302653 * 0.2 / sqrt(3).
    # 1e-9: float64 arithmetic on numbers of order 1.
    d = np.array([[0.0, 0.2, np.nan], [0.3, 0.3, 0.3], [0.4, 0.6, 0.5]])
    lo, hi = seed_interval(d)
    half = 4.302653 * 0.2 / np.sqrt(3)
    assert lo == pytest.approx(0.3 - half, abs=1e-6) and hi == pytest.approx(0.3 + half, abs=1e-6)
    assert np.isnan(seed_interval(d[:1])).all()  # one seed: no spread to estimate
    with pytest.raises(ValueError, match="seeds, scenes"):
        seed_interval(np.zeros(3))


def test_with_three_seeds_the_seed_level_interval_is_the_wider_one():
    # Seeds that disagree (+-0.15 dB) and 60 scenes each: the crossed bootstrap resamples
    # only 3 seed means and understates their spread; Student's t with 2 degrees of freedom
    # does not (the difference the verdict tables now show side by side).
    rng = np.random.default_rng(4)
    d = rng.normal(0, 0.3, size=(3, 60)) + np.array([[-0.15], [0.0], [0.15]])
    lo, hi = bootstrap_interval(d, samples=5000)
    slo, shi = seed_interval(d)
    assert shi - slo > 1.5 * (hi - lo)


def _row(mean, low, high, seeds=3, metric="psnr"):
    return Comparison("standard", metric, "full", mean, mean - 0.01, mean + 0.01, 60, seeds,
                      0.5, low, high)


def test_the_pre_registered_rule():
    # supports: mean >= +0.3 and the seed-level lower bound > 0
    assert _row(0.35, 0.05, 0.65).label == "supports"
    assert _row(0.25, 0.05, 0.45).label == "inconclusive"  # above 0, but under +0.3
    assert _row(0.35, -0.05, 0.75).label == "inconclusive"  # the interval reaches 0
    # refutes: the seed-level upper bound < +0.1
    assert _row(0.0, -0.08, 0.08).label == "refutes"
    assert _row(0.0, -0.12, 0.12).label == "inconclusive"
    assert _row(0.0, -0.08, 0.08, metric="ssim").label == ""
    assert _row(0.5, 0.4, 0.6, seeds=1).label == "needs >= 2 seeds"
    # better / worse are read from the seed-level interval, not the (narrow) bootstrap
    assert _row(0.2, -0.1, 0.5).verdict == "no difference shown"
    assert _row(0.2, 0.1, 0.3).verdict == "better"
    assert _row(-0.2, -0.3, -0.1).verdict == "worse"
    assert _row(0.2, float("nan"), float("nan"), seeds=1).verdict == "better (one seed)"
    assert "seed-level" in table([_row(0.35, 0.05, 0.65)])
