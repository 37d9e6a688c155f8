"""``usplat_dr.training.cores``: when the cores are kept awake, and that the spinners run at idle
priority on their own core and never outlive the process that started them (not even a killed
one)."""

import os
import signal
import subprocess
import sys
import time

import pytest

from usplat_dr.training import cores as _cores

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="SCHED_IDLE and sched_setaffinity are Linux's")


def _gone(pid: int, timeout: float) -> bool:
    """True once ``pid`` has exited (or is a zombie) within ``timeout`` seconds."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            with open(f"/proc/{pid}/stat") as f:
                if f.read().split(") ", 1)[1][0] == "Z":
                    return True
        except FileNotFoundError:
            return True
        time.sleep(0.05)
    return False


def _state(pid: int) -> str:
    with open(f"/proc/{pid}/stat") as f:
        return f.read().split(") ", 1)[1][0]


def test_wanted_only_for_cpu_jobs_that_own_the_machine(monkeypatch):
    monkeypatch.setattr(_cores, "available_cpus", lambda: [0, 1])
    monkeypatch.setattr(_cores.sys, "platform", "linux")
    assert _cores.wanted(None, 2, "cpu")
    assert not _cores.wanted(None, 1, "cpu")  # one thread: no waits between threads
    assert not _cores.wanted(None, 2, "cuda")
    monkeypatch.setattr(_cores, "available_cpus", lambda: list(range(64)))
    assert not _cores.wanted(None, 8, "cpu")  # 8 of 64 cores: others may use the rest
    assert _cores.wanted(True, 1, "cuda") and not _cores.wanted(False, 2, "cpu")
    monkeypatch.setattr(_cores.sys, "platform", "darwin")
    monkeypatch.setattr(_cores, "available_cpus", lambda: [0, 1])
    assert not _cores.wanted(None, 2, "cpu")


@linux_only
def test_spinners_are_idle_priority_pinned_and_stop():
    cpus = _cores.available_cpus()[:2]
    keeper = _cores.CoreKeeper(cpus).start()
    try:
        assert len(keeper.procs) == len(cpus)
        for proc, cpu in zip(keeper.procs, cpus):
            assert os.sched_getscheduler(proc.pid) == os.SCHED_IDLE
            assert os.sched_getaffinity(proc.pid) == {cpu}
            assert _state(proc.pid) in "RS"  # running (or between time slices)
        keeper.start()  # a second start adds nothing
        assert len(keeper.procs) == len(cpus)
    finally:
        pids = [p.pid for p in keeper.procs]
        keeper.stop()
    assert keeper.procs == [] and all(_gone(pid, 2.0) for pid in pids)


@linux_only
def test_spinners_exit_when_their_parent_is_killed():
    code = ("import os, sys, time\n"
            "from usplat_dr.training.cores import CoreKeeper\n"
            "k = CoreKeeper().start()\n"
            "print(' '.join(str(p.pid) for p in k.procs), flush=True)\n"
            "time.sleep(60)\n")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    pids = [int(p) for p in parent.stdout.readline().split()]
    assert pids, "no spinner started"
    assert not any(_gone(pid, 0.2) for pid in pids)  # they spin while the parent lives
    parent.send_signal(signal.SIGKILL)  # no cleanup code runs in the parent
    parent.wait()
    # each spinner checks its parent about every millisecond of spinning; 5 s is slack for a
    # loaded CI machine, not the expected time (tens of milliseconds)
    assert all(_gone(pid, 5.0) for pid in pids)
