"""``train/bench/examples_per_cpu.py`` and ``train/bench/shared_machine.py``: arm names, the CPU
time of a run across resumes against hand-worked values, the table's ratios, and the
shared-machine benchmark's busy condition."""

import importlib.util
import os
import time
from pathlib import Path

import pytest

BENCH = Path(__file__).parents[2] / "train" / "bench"


def load(name: str):
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


epc = load("examples_per_cpu")


def test_arm_names():
    assert epc.parse_arm("t2b1") == {"name": "t2b1", "threads": 2, "batch": 1, "lr": None,
                                     "portable": False}
    arm = epc.parse_arm("t1b4lr2e-3p")
    assert (arm["threads"], arm["batch"], arm["lr"], arm["portable"]) == (1, 4, 0.002, True)
    for bad in ("t1", "b4", "t1b4lr", "t1b4x"):
        with pytest.raises(Exception, match="is not t<threads>b<batch>"):
            epc.parse_arm(bad)


def test_overrides_set_the_arm_and_keep_the_recipe():
    over = epc.overrides(epc.parse_arm("t1b4lr2e-3"), "data", "out", 600, 3)
    assert {"threads=1", "data_loader.batch_size=4", "seed=3", "train.steps=600",
            "train.checkpoint_every=100", "optimizer.lr=0.002"} <= set(over)
    assert not any(o.startswith("optimizer.lr") for o in epc.overrides(
        epc.parse_arm("t2b1"), "data", "out", 600, 0))


def test_cpu_time_per_step_is_read_from_the_run_log(tmp_path):
    (tmp_path / "metrics.csv").write_text(
        "step,loss,cpu_s\n10,1,2.0\n20,1,4.1\n30,1,6.2\n40,1,\n")
    assert epc.cpu_at_steps(tmp_path) == {10: 2.0, 20: 4.1, 30: 6.2}


def test_cpu_at_a_checkpoint_between_logged_steps():
    logged = {10: 2.0, 20: 4.0, 30: 7.0}
    assert epc.cpu_at(logged, 20) == 4.0
    assert epc.cpu_at(logged, 25) == 5.5  # halfway between 4.0 and 7.0
    assert epc.cpu_at(logged, 5) is None and epc.cpu_at(logged, 31) is None


def test_table_gives_rates_and_differences_against_the_baseline(capsys):
    points = [{"run": "t2b1_seed0", "step": "100", "examples": "100", "cpu_s": "50",
               "psnr": "20.0"},
              {"run": "t2b1_seed0", "step": "200", "examples": "200", "cpu_s": "100",
               "psnr": "21.0"},
              {"run": "t1b4_seed0", "step": "100", "examples": "400", "cpu_s": "100",
               "psnr": "21.5"}]
    epc.table(points, "t2b1")
    out = capsys.readouterr().out.splitlines()
    row = next(line for line in out if line.startswith("t1b4_seed0"))
    # 400 examples / 100 CPU-s = 4.00 against 200 / 100 = 2.00: 2.00x, +0.50 dB
    assert "4.00" in row and "2.00x +0.50 dB" in row
    assert "1.00x +0.00 dB" in next(line for line in out if line.startswith("t2b1_seed0"))


def _children() -> list[Path]:
    return [p for p in Path("/proc").iterdir() if p.name.isdigit() and (p / "stat").is_file()
            and (p / "stat").read_text().rsplit(")", 1)[1].split()[1] == str(os.getpid())]


def test_the_busy_condition_runs_one_cpu_bound_process_for_the_block():
    shared = load("shared_machine")
    before = set(_children())
    with shared.condition("busy"):
        burner = set(_children()) - before
        assert len(burner) == 1
        (child,) = burner
        ticks0 = sum(int(v) for v in (child / "stat").read_text().rsplit(")", 1)[1].split()[11:13])
        time.sleep(0.5)
        ticks1 = sum(int(v) for v in (child / "stat").read_text().rsplit(")", 1)[1].split()[11:13])
        # utime + stime in clock ticks (100 per second): a CPU-bound process gets well over a
        # tenth of a core over 0.5 s even on a loaded 2-core machine
        assert ticks1 - ticks0 >= 5
    assert not (set(_children()) - before)  # killed and reaped when the block ends
    with shared.condition("quiet"):
        assert set(_children()) == before
