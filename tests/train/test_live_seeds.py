"""train/studies/live_seeds.py: a seed counts only when its branch is live on the standard
split; over the live seeds the verdict's rule reads the seed-level t interval (checked against
the interval computed here from the per-seed means with scipy); with one live seed the
interval over that seed's scenes decides and the label says so."""

import csv
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "live_seeds.py"
spec = importlib.util.spec_from_file_location("live_seeds", SCRIPT)
study = importlib.util.module_from_spec(spec)
spec.loader.exec_module(study)

SCENES = [f"indoor_{k:03d}" for k in range(8)]


def write_eval(folder: Path, psnr: dict, live: bool) -> Path:
    """A ``usplat eval --out`` folder: ``psnr`` split -> per-scene values; the meter's summary
    live (or not) on every split."""
    folder.mkdir(parents=True)
    with open(folder / "per_scene.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["split", "scene", "psnr"])
        w.writeheader()
        for split, values in psnr.items():
            for scene, v in zip(SCENES, values):
                w.writerow({"split": split, "scene": scene, "psnr": v})
    meter = {"spread_rel_w": {"to_gaussians.0": 0.01 if live else 1e-5},
             "d_mean": {"mean_db": 0.0, "low": -0.01, "high": 0.01},
             "d_mean_abs": {"mean_db": 0.09 if live else 0.001, "low": 0.06 if live else 0.0},
             "d_zero": {"mean_db": 0.1}, "live": live}
    summary = {"splits": {s: {"view_specificity": meter} for s in psnr}}
    (folder / "summary.json").write_text(json.dumps(summary))
    return folder


def test_only_live_seeds_count_and_the_rule_reads_their_seed_interval(tmp_path):
    rng = np.random.default_rng(0)
    base = {s: 25 + rng.normal(size=8) for s in study.SPLITS}
    a = write_eval(tmp_path / "a", base, live=False)
    offsets = {"0": 0.5, "1": 0.4, "2": -3.0, "3": 0.45}  # seed 2 is not live: left out
    folders = {}
    for seed, off in offsets.items():
        noise = {s: base[s] + off + 0.01 * rng.normal(size=8) for s in study.SPLITS}
        folders[seed] = write_eval(tmp_path / f"c{seed}", noise, live=seed != "2")
    out = tmp_path / "out"
    assert study.main(["--baseline", str(a), "--seeds",
                       *[f"{k}={v}:cuda" for k, v in folders.items()],
                       "--confirm", "1", "2", "3", "--out", str(out)]) == 0
    result = json.loads((out / "live_seeds.json").read_text())
    assert result["live"] == ["0", "1", "3"]
    means = [result["seeds"][k]["splits"]["standard"]["c_minus_a"] for k in ("0", "1", "3")]
    half = stats.t.ppf(0.975, 2) * np.std(means, ddof=1) / np.sqrt(3)
    lab = result["labels"]["standard, all live seeds"]
    # the same numbers through another route: float64 sums, to rounding
    assert np.isclose(lab["low"], np.mean(means) - half, atol=1e-9)
    assert np.isclose(lab["high"], np.mean(means) + half, atol=1e-9)
    assert lab["label"] == "supports"  # mean about +0.45 >= 0.3, lower bound > 0
    assert result["labels"]["wide_baseline, confirming live seeds"]["names"] == ["1", "3"]
    # every seed, live or not, is the exploratory row only: seed 2's -3 dB pulls it down
    explore = result["labels"]["standard, every seed (exploratory: live or not)"]
    assert explore["seeds"] == 4 and explore["mean"] < 0
    assert "| 2 | cuda | standard |" in (out / "live_seeds.md").read_text()


def test_one_live_seed_is_read_on_its_scenes_and_said(tmp_path):
    base = {s: np.full(8, 25.0) + np.arange(8) * 0.1 for s in study.SPLITS}
    a = write_eval(tmp_path / "a", base, live=False)
    diffs = np.array([0.0, 0.02, -0.02, 0.01, -0.01, 0.03, -0.03, 0.0])  # mean 0: refutes
    c = write_eval(tmp_path / "c", {s: base[s] + diffs for s in study.SPLITS}, live=True)
    out = tmp_path / "out"
    study.main(["--baseline", str(a), "--seeds", f"0={c}", "--controls", f"ctl={c}",
                "--out", str(out)])
    result = json.loads((out / "live_seeds.json").read_text())
    lab = result["labels"]["standard, all live seeds"]
    # a control is read against (a) on the same scenes: here the same folder as the seed
    assert np.isclose(result["controls"]["ctl"]["standard"]["minus_a"], diffs.mean())
    low, high = stats.t.interval(0.95, 7, loc=diffs.mean(), scale=stats.sem(diffs))
    assert np.isclose(lab["low"], low, atol=1e-9) and np.isclose(lab["high"], high, atol=1e-9)
    assert lab["label"] == "refutes (one live seed: interval over scenes)"


def test_paired_baselines_read_each_seed_against_its_own_a(tmp_path):
    """--baseline SEED=FOLDER: (c) - (a) per seed against that seed's (a); --live-split picks
    the split whose meter decides which seeds count."""
    rng = np.random.default_rng(1)
    folders, baselines, expected = {}, {}, {}
    for seed, off in (("0", 0.2), ("1", 0.3), ("2", 0.4)):
        base = {s: 25 + rng.normal(size=8) for s in study.SPLITS}
        d = off + 0.05 * rng.normal(size=8)
        expected[seed] = d.mean()
        baselines[seed] = write_eval(tmp_path / f"a{seed}", base, live=False)
        folders[seed] = write_eval(tmp_path / f"c{seed}", {s: base[s] + d for s in base},
                                   live=True)
    out = tmp_path / "out"
    assert study.main(["--baseline", *[f"{k}={v}" for k, v in baselines.items()],
                       "--live-split", "extrapolation",
                       "--seeds", *[f"{k}={v}" for k, v in folders.items()],
                       "--out", str(out)]) == 0
    result = json.loads((out / "live_seeds.json").read_text())
    assert result["paired"] and result["live_split"] == "extrapolation"
    for seed, mean in expected.items():
        # each seed against its own (a): a shared (a) would mix the seeds' base noise in
        got = result["seeds"][seed]["splits"]["standard"]["c_minus_a"]
        assert np.isclose(got, mean, atol=1e-9)
    means = list(expected.values())
    half = stats.t.ppf(0.975, 2) * np.std(means, ddof=1) / np.sqrt(3)
    lab = result["labels"]["standard, all live seeds"]
    assert np.isclose(lab["low"], np.mean(means) - half, atol=1e-9)


def test_a_seed_without_its_own_baseline_is_an_error(tmp_path):
    base = {s: np.full(8, 25.0) for s in study.SPLITS}
    a = write_eval(tmp_path / "a", base, live=False)
    c = write_eval(tmp_path / "c", base, live=True)
    with pytest.raises(SystemExit):
        study.main(["--baseline", f"0={a}", "--seeds", f"1={c}", "--out", str(tmp_path / "o")])


def test_fewer_live_seeds_than_registered_is_not_readable(tmp_path):
    """Two live seeds whose rule would read "supports" are "not readable" under --min-live 3
    (the 128x128 registration), and read as before under the default."""
    rng = np.random.default_rng(1)
    base = {s: 25 + rng.normal(size=8) for s in study.SPLITS}
    a = write_eval(tmp_path / "a", base, live=False)
    folders = [write_eval(tmp_path / f"c{k}", {s: base[s] + off + 0.01 * rng.normal(size=8)
                                               for s in study.SPLITS}, live=True)
               for k, off in enumerate((0.5, 0.45))]
    seeds = [f"{k}={f}" for k, f in enumerate(folders)]
    for extra, out in (([], tmp_path / "default"), (["--min-live", "3"], tmp_path / "three")):
        assert study.main(["--baseline", str(a), "--seeds", *seeds, *extra,
                           "--out", str(out)]) == 0
    read = json.loads((tmp_path / "default" / "live_seeds.json").read_text())["labels"]
    held = json.loads((tmp_path / "three" / "live_seeds.json").read_text())["labels"]
    assert read["standard, all live seeds"]["label"] == "supports"
    lab = held["standard, all live seeds"]
    assert lab["label"].startswith("not readable: 2 live, the rule reads at 3")
    assert "(would read supports)" in lab["label"]
    # the numbers are the same either way; only the label waits
    assert lab["mean"] == read["standard, all live seeds"]["mean"]
    with pytest.raises(SystemExit):
        study.main(["--baseline", str(a), "--seeds", *seeds, "--min-live", "0",
                    "--out", str(tmp_path / "bad")])
