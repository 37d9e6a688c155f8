"""``usplat_dr.training.cores``: when the cores are kept awake (the setting, or the wake-up
probe's measurement, injected), that the probe measures, and that the spinners run at idle
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


def _probe(median_us: float) -> _cores.WakeProbe:
    return _cores.WakeProbe(float(median_us), 100, (0, 1), median_us / 2, median_us * 2.0)


@pytest.fixture
def vm(monkeypatch):
    """A two-core Linux VM whose probe (injected) finds idle cores slow to wake."""
    monkeypatch.setattr(_cores, "available_cpus", lambda: [0, 1])
    monkeypatch.setattr(_cores.sys, "platform", "linux")
    monkeypatch.setattr(_cores, "hypervisor", lambda: True)
    monkeypatch.setattr(_cores, "cpuidle_driver", lambda: "haltpoll")
    monkeypatch.setattr(_cores, "probe_wake_latency", lambda: _probe(140))
    return monkeypatch


def test_wanted_only_for_cpu_jobs_that_own_the_machine(vm):
    assert _cores.wanted("auto", 2, "cpu") and _cores.wanted(None, 2, "cpu")
    assert not _cores.wanted("auto", 1, "cpu")  # one thread: no waits between threads
    assert not _cores.wanted("auto", 2, "cuda")
    vm.setattr(_cores, "available_cpus", lambda: list(range(64)))
    assert not _cores.wanted("auto", 8, "cpu")  # 8 of 64 cores: others may use the rest
    assert _cores.wanted(True, 1, "cuda") and not _cores.wanted(False, 2, "cpu")
    vm.setattr(_cores.sys, "platform", "darwin")
    vm.setattr(_cores, "available_cpus", lambda: [0, 1])
    assert not _cores.wanted("auto", 2, "cpu")


def test_auto_follows_the_probe(vm):
    above, below = _cores.WAKE_THRESHOLD_US * 2, _cores.WAKE_THRESHOLD_US / 2
    on, why = _cores.decide("auto", 2, "cpu", measure=lambda: _probe(above))
    assert on and "above 60 us" in why and "halts idle vCPUs" in why and "haltpoll" in why
    on, why = _cores.decide("auto", 2, "cpu", measure=lambda: _probe(below))
    assert not on and "below 60 us" in why
    assert _cores.decide("auto", 2, "cpu", measure=lambda: None) == (
        False, "the wake-up probe could not run here")
    vm.setattr(_cores, "hypervisor", lambda: False)  # slow wakes on bare metal: deep C-states
    on, why = _cores.decide("auto", 2, "cpu", measure=lambda: _probe(above))
    assert not on and "bare metal" in why
    vm.setattr(_cores, "hypervisor", lambda: None)  # no flags line (not x86): the probe decides
    assert _cores.decide("auto", 2, "cpu", measure=lambda: _probe(above))[0]


def test_an_explicit_setting_wins_without_probing(vm):
    def probe():
        pytest.fail("probed although keep_cores_awake decided")

    vm.setattr(_cores, "probe_wake_latency", probe)
    assert _cores.decide(True, 2, "cpu") == (True, "keep_cores_awake=true")
    assert _cores.decide(False, 2, "cpu") == (False, "keep_cores_awake=false")
    assert _cores.decide(True, 1, "cuda")[0]  # even where auto would not probe


def test_the_log_line_says_on_or_off_and_why(vm):
    assert _cores.log_line(*_cores.decide("auto", 2, "cpu")) == (
        "core keeper on: idle cores woke in 140 us (median of 100), above 60 us: this machine "
        "halts idle vCPUs (cpuidle driver haltpoll)")
    assert _cores.log_line(*_cores.decide("auto", 2, "cpu", measure=lambda: _probe(12.4))) == (
        "core keeper off: idle cores woke in 12 us (median of 100), below 60 us")


@linux_only
def test_the_probe_measures_a_positive_latency_quickly():
    if len(_cores.available_cpus()) < 2:
        pytest.skip("the probe needs two CPUs")
    start = time.monotonic()
    probe = _cores.probe_wake_latency(rounds=20)
    took = time.monotonic() - start
    assert probe is not None and probe.rounds == 20
    assert 0 < probe.low_us <= probe.median_us <= probe.high_us < float("inf")
    # ~0.1 s here (20 gaps of 1-3 ms and a Python start); the bound is slack for a loaded
    # machine, not the expected time
    assert took < 5.0, took


def test_the_probe_needs_two_cpus():
    assert _cores.probe_wake_latency(cpus=[0]) is None


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
