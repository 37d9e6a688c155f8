"""train/studies/budget_chart.py: the points it draws are the means and differences of the
rows it reads, matched by scene, and it writes the chart."""

import csv
import importlib.util
from pathlib import Path

import pytest

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "budget_chart.py"
spec = importlib.util.spec_from_file_location("budget_chart", SCRIPT)
chart = importlib.util.module_from_spec(spec)
spec.loader.exec_module(chart)


def write(path: Path, rows: list[dict]) -> None:
    path.mkdir(parents=True, exist_ok=True)
    with open(path / "per_scene.csv", "w", newline="") as f:
        w = csv.DictWriter(f, list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def test_eval_point_matches_scenes_and_counts_what_was_rendered(tmp_path):
    write(tmp_path / "all", [{"split": "standard", "scene": s, "psnr": p}
                             for s, p in (("a", 25.0), ("b", 20.0), ("c", 30.0))])
    # scene c was not evaluated with the budget: left out; a loses 0.5 dB, b gains 0.1
    write(tmp_path / "auto", [
        {"split": "standard", "scene": "a", "psnr": 24.5, "auto_keep": 0.5,
         "gaussians_kept": 4096, "gaussians_rendered": 3000.0, "gaussians_total": 8192},
        {"split": "standard", "scene": "b", "psnr": 20.1, "auto_keep": 1.0,
         "gaussians_kept": 8192, "gaussians_rendered": 7000.0, "gaussians_total": 8192}])
    kept, loss, worst, n = chart.eval_point(tmp_path / "all", tmp_path / "auto")
    assert n == 2
    assert kept == pytest.approx((3000 + 7000) / 2 / 8192)
    assert loss == pytest.approx((0.5 - 0.1) / 2)
    assert worst == pytest.approx(0.5)


def test_the_chart_is_written_from_the_committed_rows(tmp_path, capsys):
    out = tmp_path / "chart.png"
    assert chart.main(["--out", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = capsys.readouterr().out
    # the dither ranking's mean loss at 50% over the 20 committed held-out scenes
    with open(chart.HERE / "heldout_proxy.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    half = [float(r["real_loss"]) for r in rows if float(r["keep"]) == 0.5]
    assert f"0.5: {sum(half) / len(half):+.2f}" in text
