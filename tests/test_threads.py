"""``usplat_dr._threads``. How torch's OpenMP workers wait: GOMP_SPINCOUNT is set before torch
loads, never over a user's choice, and the rasteriser says when torch came first. How many
threads: the counters parsed from ``/proc/stat`` text, a cgroup quota, the choice for each
setting and load, a real busy process seen as busy (and this process's own work not), and
``usplat``'s commands and the trainer using the choice."""

import os
import subprocess
import sys
import threading
import time

import pytest

from usplat_dr import _threads


@pytest.fixture
def clean(monkeypatch):
    for var in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY", _threads.SPIN_ENV_VAR):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.delitem(sys.modules, "torch", raising=False)  # as if torch were not loaded
    monkeypatch.setattr(_threads, "outcome", _threads.outcome)  # restored after the test
    return monkeypatch


def test_sets_the_default_spin_count(clean):
    assert _threads.configure() == _threads.DEFAULT_SPIN
    assert os.environ["GOMP_SPINCOUNT"] == _threads.DEFAULT_SPIN
    assert _threads.describe() == ("GOMP_SPINCOUNT=30000, OMP_WAIT_POLICY unset: set by "
                                  "usplat_dr (USPLAT_OMP_SPIN, default 30000)")


def test_users_choice_wins(clean):
    clean.setenv(_threads.SPIN_ENV_VAR, "1234")
    assert _threads.configure() == "1234"
    clean.setenv("GOMP_SPINCOUNT", "7")
    assert _threads.configure() is None and os.environ["GOMP_SPINCOUNT"] == "7"
    clean.delenv("GOMP_SPINCOUNT")
    clean.setenv("OMP_WAIT_POLICY", "PASSIVE")
    assert _threads.configure() is None and "GOMP_SPINCOUNT" not in os.environ
    assert _threads.describe() == ("GOMP_SPINCOUNT unset, OMP_WAIT_POLICY=PASSIVE: set outside "
                                  "usplat_dr (it wins)")


def test_off_and_too_late_leave_libgomp_alone(clean):
    clean.setenv(_threads.SPIN_ENV_VAR, "off")
    assert _threads.configure() is None and "GOMP_SPINCOUNT" not in os.environ
    clean.delenv(_threads.SPIN_ENV_VAR)
    clean.setitem(sys.modules, "torch", object())  # torch (and libgomp) already loaded
    assert _threads.configure() is None and "GOMP_SPINCOUNT" not in os.environ
    assert "torch was imported before it" in _threads.describe()


def test_bad_value_names_the_variable_and_changes_nothing(clean):
    clean.setenv(_threads.SPIN_ENV_VAR, "fast")
    with pytest.warns(UserWarning, match="USPLAT_OMP_SPIN='fast' is not a non-negative"):
        assert _threads.configure() is None
    assert "GOMP_SPINCOUNT" not in os.environ  # libgomp's default
    assert "libgomp's default is used" in _threads.describe()


def test_import_sets_it_before_torch():
    env = {k: v for k, v in os.environ.items()
           if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY", _threads.SPIN_ENV_VAR)}
    code = "import usplat_dr, os, sys; print(os.environ['GOMP_SPINCOUNT'], 'torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == [_threads.DEFAULT_SPIN, "False"]


@pytest.mark.parametrize(("first", "warned"), [("torch", True), ("usplat_dr", False)])
def test_the_rasteriser_says_when_torch_came_first(first, warned):
    # torch imported first: libgomp keeps its long spin, which slows the rasteriser at two
    # threads; the torch entry says so once, with the fix. In usplat_dr's order it is silent.
    env = {k: v for k, v in os.environ.items()
           if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY", _threads.SPIN_ENV_VAR)}
    second = "usplat_dr" if first == "torch" else "torch"
    code = (f"import {first}, {second}, logging, torch; logging.basicConfig(); "
            "torch.set_num_threads(2); "
            "from usplat_dr.render.scenes import pixel_aligned_scene; "
            "from usplat_dr.render import rasterize; "
            "s = pixel_aligned_scene(8, 8, seed=0); rasterize(*s.args()); rasterize(*s.args())")
    err = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stderr
    assert err.count("torch was imported before usplat_dr") == (1 if warned else 0)


# ---- how many threads ----------------------------------------------------------------------

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
    assert _threads._cpu_counters({0}, stat) == (380, 890)
    assert _threads._cpu_counters({0, 1}, stat) == (380 + 150, 890 + 650)
    assert _threads._cpu_counters({5}, stat) == (0, 0)


@pytest.mark.parametrize(("text", "cores"), [("max 100000\n", None), ("150000 100000\n", 1.5),
                                             ("50000 100000", 0.5), ("garbage", None)])
def test_cgroup_quota(tmp_path, text, cores):
    (tmp_path / "cpu.max").write_text(text)
    assert _threads.cgroup_quota(tmp_path) == cores
    assert _threads.cgroup_quota(tmp_path / "missing") is None


def test_allowed_cores_is_the_affinity_capped_by_the_quota(monkeypatch):
    monkeypatch.setattr(_threads.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})
    assert _threads.affinity_cores() == 4
    monkeypatch.setattr(_threads, "cgroup_quota", lambda: None)
    assert _threads.allowed_cores() == 4
    monkeypatch.setattr(_threads, "cgroup_quota", lambda: 1.5)  # --cpus 1.5: two threads
    assert _threads.allowed_cores() == 2
    monkeypatch.setattr(_threads, "cgroup_quota", lambda: 0.2)
    assert _threads.allowed_cores() == 1


@pytest.mark.parametrize(("busy", "threads"), [(0.0, 4), (0.4, 4), (0.6, 3), (1.0, 3),
                                               (2.5, 2), (2.6, 1), (3.9, 1), (7.0, 1), (None, 4)])
def test_auto_takes_the_free_cores(monkeypatch, busy, threads):
    monkeypatch.setattr(_threads, "affinity_cores", lambda: 4)
    monkeypatch.setattr(_threads, "cgroup_quota", lambda: None)
    choice = _threads.choose("auto", measure=lambda: busy)
    assert choice.threads == threads
    assert choice.busy == busy
    assert "threads: " in choice.line()


def test_under_a_quota_load_on_other_cpus_takes_nothing(monkeypatch):
    # a container limited to 2 cores on a 16-CPU host: 10 CPUs busy elsewhere leave its 2; 15
    # busy leave one free CPU
    monkeypatch.setattr(_threads, "affinity_cores", lambda: 16)
    monkeypatch.setattr(_threads, "cgroup_quota", lambda: 2.0)
    assert _threads.choose("auto", measure=lambda: 10.0).threads == 2
    assert _threads.choose("auto", measure=lambda: 15.0).threads == 1


def test_a_number_or_all_decides_and_anything_else_names_the_variable(monkeypatch):
    monkeypatch.setattr(_threads, "allowed_cores", lambda: 2)

    def never():
        raise AssertionError("a fixed setting must not sample the load")

    monkeypatch.setattr(os, "cpu_count", lambda: 4)
    assert _threads.choose("3", measure=never).threads == 3  # the user's choice, if <= CPUs
    with pytest.raises(ValueError, match="USPLAT_THREADS=5 is more than this machine's 4 CPUs"):
        _threads.choose("5")  # (drjit fails to start thousands of threads)
    assert _threads.choose("all", measure=never).threads == 2
    monkeypatch.setenv(_threads.THREADS_ENV_VAR, "1")
    assert _threads.choose(measure=never).threads == 1
    for bad in ("0", "two", "-1"):
        with pytest.raises(ValueError, match="USPLAT_THREADS must be a number"):
            _threads.choose(bad)


def test_one_allowed_core_is_not_sampled(monkeypatch):
    monkeypatch.setattr(_threads, "allowed_cores", lambda: 1)
    assert _threads.choose("auto", measure=lambda: 1 / 0).threads == 1


def _spin(stop: threading.Event) -> None:
    while not stop.is_set():
        sum(range(1000))


def test_a_busy_process_counts_and_this_process_does_not():
    burner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.2)  # the burner running
        busy = _threads.busy_cores(0.5)
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
        before = _threads.busy_cores(0.5)
    finally:
        stop.set()
        spinner.join()
    quiet = _threads.busy_cores(0.5)
    # Own spinning thread: about 1 core of counters, subtracted again; what remains is other
    # processes' load, which can change between the two samples (0.6: half a core of drift
    # plus rounding of the 10 ms ticks).
    assert before is not None and quiet is not None and before <= quiet + 0.6


def test_usplat_commands_and_the_trainer_use_the_choice(monkeypatch, tmp_path):
    import drjit as dr
    import torch

    from usplat_dr import cli
    from usplat_dr.training import distributed

    monkeypatch.setenv(_threads.THREADS_ENV_VAR, "1")
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
