"""train/studies/res128/stop_rule.py: window means of metrics.csv rows, and the first window
that gains less than the bound over the one before."""

import importlib.util
from pathlib import Path

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "res128" / "stop_rule.py"
spec = importlib.util.spec_from_file_location("stop_rule", SCRIPT)
rule = importlib.util.module_from_spec(spec)
spec.loader.exec_module(rule)


def rows(psnr_of_step, last=4000):
    return [{"step": str(s), "psnr": str(psnr_of_step(s))} for s in range(10, last + 1, 10)]


def test_window_means_cover_complete_windows_only():
    means = rule.window_means(rows(lambda s: s / 1000), 1000)
    assert sorted(means) == [1000, 2000, 3000, 4000]
    # steps 10, 20, ..., 1000: mean step 505
    assert abs(means[1000] - 0.505) < 1e-12 and abs(means[2000] - 1.505) < 1e-12


def test_stops_at_the_first_window_that_gains_too_little():
    # rising until step 3000, then flat: the window 3001-4000 still gains 0.495 dB over the
    # one before (mean 3.0 against 2.505), the window 4001-5000 nothing
    means = rule.window_means(rows(lambda s: min(s, 3000) / 1000, last=5000), 1000)
    assert rule.stop_step(means, 0.05) == 5000
    assert rule.stop_step({1000: 20.0, 2000: 20.2}, 0.05) is None
    assert rule.stop_step({1000: 20.0, 2000: 20.04}, 0.05) == 2000


def test_the_command_says_whether_to_stop(tmp_path, capsys):
    path = tmp_path / "metrics.csv"
    path.write_text("step,psnr\n" + "".join(f"{s},{20 + min(s, 1000) / 1000}\n"
                                            for s in range(10, 3001, 10)))
    assert rule.main([str(path)]) == 0 and "stop at step 3000" in capsys.readouterr().out
    assert rule.main([str(path), "--min-gain", "-1"]) == 1
