"""``train/studies/oracle_convergence.py``: per-scene means over targets, paired across two step
counts, and the t interval, against values worked by hand."""

import importlib.util
import math
from pathlib import Path

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "oracle_convergence.py"
spec = importlib.util.spec_from_file_location("oracle_convergence", SCRIPT)
convergence = importlib.util.module_from_spec(spec)
spec.loader.exec_module(convergence)


def write(path: Path, gaps: dict[str, list[float]]) -> None:
    lines = ["scene,target,a,shared_half,per_target,shared"]
    for scene, values in gaps.items():
        lines += [f"{scene},{i},20.0,30.0,{31.0 + g},31.0" for i, g in enumerate(values)]
    path.write_text("\n".join(lines) + "\n")


def test_scenes_are_paired_and_the_interval_is_the_t_interval(tmp_path, capsys):
    write(tmp_path / "before.csv", {"s0": [0.1, 0.3], "s1": [0.4, 0.4], "s2": [0.5, 0.7]})
    write(tmp_path / "after.csv", {"s1": [0.6, 0.6], "s0": [0.4, 0.6], "s2": [0.9, 0.9]})
    before = convergence.per_scene(str(tmp_path / "before.csv"))
    assert all(math.isclose(before[k], v, abs_tol=1e-9)  # CSV floats: 1 ulp of 31
               for k, v in {"s0": 0.2, "s1": 0.4, "s2": 0.6}.items())
    assert convergence.main(["--before", str(tmp_path / "before.csv"),
                             "--after", str(tmp_path / "after.csv")]) == 0
    out = capsys.readouterr().out
    # moved by 0.3, 0.2, 0.3 per scene: mean 0.2667, sd 0.0577, t(0.975, 2) = 4.3027
    half = 4.302653 * math.sqrt(1 / 300) / math.sqrt(3)
    assert f"moved: +0.267 dB [{0.8 / 3 - half:+.3f}, {0.8 / 3 + half:+.3f}] over 3 scenes" in out
