"""train/studies/budget_sizes.py: the budget's loss at two sizes paired by scene, its 95% t
interval against scipy's Student t written out here, the registered rule's three labels, and
the chart and numbers it writes."""

import csv
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "budget_sizes.py"
spec = importlib.util.spec_from_file_location("budget_sizes", SCRIPT)
study = importlib.util.module_from_spec(spec)
spec.loader.exec_module(study)


def proxy_folder(path: Path, rank_by: str, losses: dict[float, dict[str, float]]) -> Path:
    """An auto_budget_proxy.py --out folder holding these losses (and the keep-1 rows)."""
    path.mkdir(parents=True)
    with open(path / "proxy.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["scene", "keep", "proxy_loss", "real_loss"])
        w.writeheader()
        for keep, by_scene in losses.items():
            for scene, loss in by_scene.items():
                w.writerow({"scene": scene, "keep": keep, "proxy_loss": 2 * loss,
                            "real_loss": loss})
        for scene in next(iter(losses.values())):
            w.writerow({"scene": scene, "keep": 1, "proxy_loss": 0, "real_loss": 0})
    (path / "summary.json").write_text(json.dumps({"rank_by": rank_by, "rows": {}}))
    return path


def test_paired_difference_and_interval_match_student_t():
    rng = np.random.default_rng(3)
    scenes = [f"s{i}" for i in range(12)]
    a = dict(zip(scenes, rng.normal(1.0, 0.3, 12)))
    b = {s: v - 0.2 + rng.normal(0, 0.1) for s, v in a.items()}
    b["only_large"] = 9.0  # unpaired scenes are left out
    row = study.compare({0.3: a}, {0.3: b})[0.3]
    d = np.array([b[s] - a[s] for s in scenes])
    half = stats.t.ppf(0.975, len(d) - 1) * d.std(ddof=1) / np.sqrt(len(d))
    assert row["scenes"] == 12 and row["unpaired"] == 1
    assert np.isclose(row["difference"], d.mean(), atol=1e-12)
    # the same float64 arithmetic in another order: 1e-9 dB is far below any reading's use
    assert abs(row["low"] - (d.mean() - half)) < 1e-9
    assert abs(row["high"] - (d.mean() + half)) < 1e-9
    assert np.isclose(row["small"], np.mean([a[s] for s in scenes]))


@pytest.mark.parametrize("low, high, expected", [
    (-0.5, -0.1, "denser pixels leave more to drop"),
    (0.1, 0.5, "denser pixels leave less to drop"),
    (-0.1, 0.2, "no difference shown")])
def test_the_registered_rule(low, high, expected):
    assert study.label(low, high) == expected


def test_the_chart_numbers_and_errors(tmp_path, capsys):
    scenes = [f"s{i}" for i in range(5)]
    keeps = (0.1, 0.3, 0.5)
    small = {k: {s: 3 * (1 - k) + 0.1 * i for i, s in enumerate(scenes)} for k in keeps}
    large = {k: {s: v - 0.5 - 0.01 * i for i, (s, v) in enumerate(small[k].items())}
             for k in keeps}
    folders = {(size, r): proxy_folder(tmp_path / f"{size}_{r}", r, d)
               for size, d in (("64", small), ("128", large)) for r in ("learned", "dither")}
    out = tmp_path / "chart.png"
    assert study.main(["--small", str(folders["64", "learned"]), str(folders["64", "dither"]),
                       "--large", str(folders["128", "learned"]),
                       str(folders["128", "dither"]), "--out", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    numbers = json.loads(out.with_suffix(".json").read_text())
    assert numbers["rule"]["label"] == "denser pixels leave more to drop"
    assert abs(numbers["rule"]["difference"] - (-0.52)) < 1e-9  # -0.5 - 0.01 * mean(0..4)
    assert set(numbers["rankings"]) == {"learned", "dither"}
    assert "denser pixels leave more to drop" in capsys.readouterr().out
    with pytest.raises(SystemExit):  # a ranking measured at one size only
        study.main(["--small", str(folders["64", "learned"]), "--large",
                    str(folders["128", "dither"]), "--out", str(out)])
    with pytest.raises(SystemExit):  # two folders of one ranking at one size
        study.main(["--small", str(folders["64", "learned"]), str(folders["64", "learned"]),
                    "--large", str(folders["128", "learned"]), "--out", str(out)])
    with pytest.raises(SystemExit):  # a fraction neither measured
        study.main(["--small", str(folders["64", "learned"]), "--large",
                    str(folders["128", "learned"]), "--rule-keep", "0.2", "--out", str(out)])
