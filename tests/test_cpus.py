"""The thread count from the free cores (``usplat_dr._cpus``): the counters parsed from
``/proc/stat`` text, a cgroup quota, the choice for each setting and load, a real busy
process seen as busy (and this process's own work not), and ``usplat``'s commands and the
trainer using the choice."""

import subprocess
import sys
import threading
import time

import pytest

from usplat_dr import _cpus

STAT = """cpu  400 0 100 1000 0 0 0 0 0 0
cpu0 300 0 50 500 10 5 5 20 7 0
cpu1 100 0 50 500 0 0 0 0 0 0
intr 12345
"""


def test_counters_sum_the_busy_fields_of_the_allowed_cpus(tmp_path):
    stat = tmp_path / "stat"
    stat.write_text(STAT)
    # cpu0: busy = user 300 + nice 0 + system 50 + irq 5 + softirq 5 + steal 20 = 380; total is
    # the first 8 fields (guest is inside user already) = 890
    assert _cpus._cpu_counters({0}, stat) == (380, 890)
    assert _cpus._cpu_counters({0, 1}, stat) == (380 + 150, 890 + 650)
    assert _cpus._cpu_counters({5}, stat) == (0, 0)


@pytest.mark.parametrize(("text", "cores"), [("max 100000\n", None), ("150000 100000\n", 1.5),
                                             ("50000 100000", 0.5), ("garbage", None)])
def test_cgroup_quota(tmp_path, text, cores):
    (tmp_path / "cpu.max").write_text(text)
    assert _cpus.cgroup_quota(tmp_path) == cores
    assert _cpus.cgroup_quota(tmp_path / "missing") is None


def test_allowed_cores_is_the_affinity_capped_by_the_quota(monkeypatch):
    monkeypatch.setattr(_cpus.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})
    monkeypatch.setattr(_cpus, "cgroup_quota", lambda: None)
    assert _cpus.allowed_cores() == 4
    monkeypatch.setattr(_cpus, "cgroup_quota", lambda: 1.5)  # --cpus 1.5: two threads
    assert _cpus.allowed_cores() == 2
    monkeypatch.setattr(_cpus, "cgroup_quota", lambda: 0.2)
    assert _cpus.allowed_cores() == 1


@pytest.mark.parametrize(("busy", "threads"), [(0.0, 4), (0.4, 4), (0.6, 3), (1.0, 3),
                                               (2.5, 2), (2.6, 1), (3.9, 1), (7.0, 1), (None, 4)])
def test_auto_takes_the_free_cores(monkeypatch, busy, threads):
    monkeypatch.setattr(_cpus, "allowed_cores", lambda: 4)
    choice = _cpus.choose("auto", measure=lambda: busy)
    assert choice.threads == threads
    assert choice.busy == busy
    assert "threads: " in choice.line()


def test_a_number_or_all_decides_and_anything_else_names_the_variable(monkeypatch):
    monkeypatch.setattr(_cpus, "allowed_cores", lambda: 2)

    def never():
        raise AssertionError("a fixed setting must not sample the load")

    assert _cpus.choose("3", measure=never).threads == 3
    assert _cpus.choose("all", measure=never).threads == 2
    monkeypatch.setenv(_cpus.ENV_VAR, "1")
    assert _cpus.choose(measure=never).threads == 1
    for bad in ("0", "two", "-1"):
        with pytest.raises(ValueError, match="USPLAT_THREADS must be a number"):
            _cpus.choose(bad)


def test_one_allowed_core_is_not_sampled(monkeypatch):
    monkeypatch.setattr(_cpus, "allowed_cores", lambda: 1)
    assert _cpus.choose("auto", measure=lambda: 1 / 0).threads == 1


def _spin(stop: threading.Event) -> None:
    while not stop.is_set():
        sum(range(1000))


def test_a_busy_process_counts_and_this_process_does_not():
    burner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.2)  # the burner running
        busy = _cpus.busy_cores(0.5)
    finally:
        burner.kill()
        burner.wait()
    # The burner is one CPU-bound process: about 1.0 core. The lower bound leaves room for
    # a loaded CI machine sharing that core with other work (the scheduler still gives the
    # burner at least half of one); /proc/stat has 10 ms resolution (2% of a 0.5 s sample).
    assert busy is not None and busy >= 0.5
    stop = threading.Event()  # this process's own work is subtracted
    spinner = threading.Thread(target=_spin, args=(stop,))
    spinner.start()
    try:
        before = _cpus.busy_cores(0.5)
    finally:
        stop.set()
        spinner.join()
    quiet = _cpus.busy_cores(0.5)
    # Own spinning thread: about 1 core of counters, subtracted again; what remains is other
    # processes' load, which can change between the two samples (0.6: half a core of drift
    # plus rounding of the 10 ms ticks).
    assert before is not None and quiet is not None and before <= quiet + 0.6


def test_usplat_commands_and_the_trainer_use_the_choice(monkeypatch, tmp_path):
    import drjit as dr
    import torch

    from usplat_dr import cli
    from usplat_dr.training import distributed

    monkeypatch.setenv(_cpus.ENV_VAR, "1")
    torch_threads, dr_threads = torch.get_num_threads(), dr.thread_count()
    try:
        torch.set_num_threads(2)
        cli.use_free_cores()
        assert torch.get_num_threads() == 1 and dr.thread_count() == 1
        torch.set_num_threads(2)
        distributed.setup_distributed("cpu", None)
        assert torch.get_num_threads() == 1
        distributed.setup_distributed("cpu", 2)  # a threads setting wins
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(torch_threads)
        dr.set_thread_count(dr_threads)
