"""The benchmark scripts' timing helper: interleaved ABBA rounds, medians of wall and process
CPU time, and the machine line."""

import itertools
import types

import pytest

from usplat_dr.evaluation import timing


def test_medians_of_the_timed_rounds_only(monkeypatch):
    # a fake clock: every reading advances 1 ms of wall and 2 ms of CPU, so each call lasts
    # exactly 1 / 2 ms, except the calls of "slow", which advance the clocks by 10 ms more
    clock = {"wall": 0.0, "cpu": 0.0}

    def tick(key, step):
        def read():
            clock[key] += step
            return clock[key]
        return read

    monkeypatch.setattr(timing, "time", types.SimpleNamespace(
        perf_counter=tick("wall", 1e-3), process_time=tick("cpu", 2e-3)))

    def slow():
        clock["wall"] += 10e-3

    calls = itertools.count()
    t = timing.interleaved({"fast": lambda: next(calls), "slow": slow}, rounds=3, warmup=2)
    assert next(calls) == 5  # 2 warm-up calls and 3 timed ones
    fast = t["fast"]
    assert (fast.wall, fast.cpu, fast.best) == pytest.approx((1.0, 2.0, 1.0))
    assert t["slow"].wall == pytest.approx(11.0) and t["slow"].cpu == pytest.approx(2.0)


def test_bad_round_counts_and_the_machine_line():
    with pytest.raises(ValueError, match="rounds must be >= 1"):
        timing.interleaved({"a": lambda: None}, rounds=0)
    line = timing.machine_line()
    assert line.startswith("# ") and "CPUs" in line and timing.cpu_isa() in line
