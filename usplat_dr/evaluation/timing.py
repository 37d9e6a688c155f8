"""Timing for the benchmark scripts, one way for all: the variants compared run interleaved
(round by round, the order reversed every other round, since the variant that runs second in
a round was measured to pay 3-5 % on these machines), each call's wall and process CPU time
recorded, medians reported; and a line naming the machine, to print beside every table.
Timings are never asserted by tests (train/bench/README.md)."""

import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Timing:
    """Medians over the timed rounds, in milliseconds: ``wall``, process ``cpu`` (about
    twice the wall time when two threads are busy), and the ``best`` wall time."""

    wall: float
    cpu: float
    best: float


def interleaved(fns: dict[str, Callable[[], object]], rounds: int, warmup: int = 1,
                alternate: bool = True) -> dict[str, Timing]:
    """Call every function of ``fns`` once per round, ``warmup`` untimed rounds then
    ``rounds`` timed ones, the order reversed every other round when ``alternate`` (ABBA);
    the ``Timing`` of each.

    Examples:
        >>> calls = []
        >>> t = interleaved({"a": lambda: calls.append("a"), "b": lambda: calls.append("b")},
        ...                 rounds=2, warmup=0)
        >>> calls, sorted(t)
        (['a', 'b', 'b', 'a'], ['a', 'b'])
    """
    if rounds < 1 or warmup < 0:
        raise ValueError(f"rounds must be >= 1 and warmup >= 0, got {rounds}, {warmup}")
    names = list(fns)
    for _ in range(warmup):
        for name in names:
            fns[name]()
    wall: dict[str, list[float]] = {n: [] for n in names}
    cpu: dict[str, list[float]] = {n: [] for n in names}
    for r in range(rounds):
        for name in (names[::-1] if alternate and r % 2 else names):
            w0, c0 = time.perf_counter(), time.process_time()
            fns[name]()
            wall[name].append(1e3 * (time.perf_counter() - w0))
            cpu[name].append(1e3 * (time.process_time() - c0))
    return {n: Timing(statistics.median(wall[n]), statistics.median(cpu[n]), min(wall[n]))
            for n in names}


def cpu_isa() -> str:
    """The widest x86 vector extension this CPU has (``avx512f``, ``avx2``...), from
    ``/proc/cpuinfo``; the machine name elsewhere."""
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line for line in f if line.startswith("flags")), "").split()
    except OSError:
        return platform.machine()
    return next((isa for isa in ("avx512f", "avx2", "avx", "sse4_2") if isa in flags),
                platform.machine())


def machine_line() -> str:
    """One line naming what a timing depends on: CPU model, widest ISA, cores, load, the
    threads torch uses (where it is imported), Python, the date.

    Examples:
        >>> machine_line().startswith("# ")
        True
    """
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            model = next((line.split(":", 1)[1].strip() for line in f
                          if line.startswith("model name")), model)
    except OSError:
        pass
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    torch = sys.modules.get("torch")
    threads = f", torch threads {torch.get_num_threads()}" if torch is not None else ""
    return (f"# {model}, {cpu_isa()}, {os.cpu_count()} CPUs, load {load:.2f}{threads}; "
            f"Python {platform.python_version()}; {time.strftime('%Y-%m-%d')}")
