"""The CPU threads of a run: how many, and how torch's OpenMP workers wait between operations.
No third-party imports (``usplat_dr/__init__`` runs ``configure`` before torch may load).

**How many** (``choose``): the cores this process may run on (affinity and a cgroup CPU quota)
less the cores other processes keep busy right now. On a shared machine a run that starts one
thread per core competes with the other processes for every core, and its threads wait for
each other at every parallel operation (torch's OpenMP barriers, Dr.Jit's kernel blocks). So
``usplat``'s commands and ``usplat train`` (``threads: null``) start one thread per *free*
core, measured over a short sample of ``/proc/stat`` (train/bench/README.md, "On a shared
machine"). ``USPLAT_THREADS`` decides instead: a number, ``all`` (one per allowed core,
whatever else runs) or ``auto`` (the default). The thread count changes the order of float
sums, so for bit-for-bit repeatable numbers set a number (docs/reproducibility.md).

**How they wait** (``configure``): torch's CPU wheels use GNU OpenMP, whose workers keep
spinning on their cores after a parallel operation (libgomp's default: 300,000 iterations,
milliseconds) before they sleep. The rasteriser runs on Dr.Jit's own thread pool, so right
after a torch operation its threads shared the two cores with spinning torch workers: at 2
threads a 64x64 forward+backward took 10.4 ms instead of 4.9, and the torch bridge added 6-13
ms over the Dr.Jit entry instead of about 1 (train/bench/README.md, "OpenMP spinning";
``train/bench/omp_spin.py``). A spin count of 30,000 kept torch's own operations as fast
(training steps 0.93-0.99x), where ``OMP_WAIT_POLICY=PASSIVE`` (no spinning) made a training
step 1.7x slower. libgomp reads ``GOMP_SPINCOUNT`` once, when it loads (with torch), so this
runs on ``import usplat_dr``, which must come before ``import torch`` for it to apply (the
rasteriser warns once where it did not). A value the user set for ``GOMP_SPINCOUNT`` or
``OMP_WAIT_POLICY`` wins; ``USPLAT_OMP_SPIN`` chooses ours (a number, or ``off`` for
libgomp's default).
"""

import math
import os
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

SPIN_ENV_VAR = "USPLAT_OMP_SPIN"
DEFAULT_SPIN = "30000"

#: What the last ``configure`` did, in words (``describe``; ``usplat doctor``).
outcome = "not configured (usplat_dr was not imported?)"


def configure() -> str | None:
    """Set ``GOMP_SPINCOUNT`` when nothing else decides it; return the value set (or None)."""
    global outcome
    choice = os.environ.get(SPIN_ENV_VAR, DEFAULT_SPIN).strip().lower()
    if choice == "off":
        outcome = f"libgomp's default ({SPIN_ENV_VAR}=off)"
        return None
    if not choice.isdigit():
        # at import a ValueError would be a traceback in every program that imports us; a
        # tuning knob set wrong leaves libgomp's default, said by a warning and by doctor
        outcome = (f"not set: {SPIN_ENV_VAR}={os.environ[SPIN_ENV_VAR]!r} is not a "
                   f"non-negative integer or 'off' (libgomp's default is used; e.g. "
                   f"{SPIN_ENV_VAR}={DEFAULT_SPIN})")
        warnings.warn(outcome, stacklevel=3)
        return None
    if "torch" in sys.modules:  # too late: torch (and libgomp) already loaded
        outcome = "not set by usplat_dr: torch was imported before it"
        return None
    if "GOMP_SPINCOUNT" in os.environ or "OMP_WAIT_POLICY" in os.environ:
        outcome = "set outside usplat_dr (it wins)"
        return None
    os.environ["GOMP_SPINCOUNT"] = choice
    outcome = f"set by usplat_dr ({SPIN_ENV_VAR}, default {DEFAULT_SPIN})"
    return choice


def torch_came_first() -> bool:
    """Whether torch (and libgomp) loaded before ``configure`` could set the spin, with
    nothing else (the user's ``GOMP_SPINCOUNT`` or ``OMP_WAIT_POLICY``, or ``off``) deciding
    it."""
    return outcome.startswith("not set by usplat_dr: torch was imported before it")


def describe() -> str:
    """The OpenMP spin setting now and who chose it, e.g. ``GOMP_SPINCOUNT=30000,
    OMP_WAIT_POLICY unset: set by usplat_dr (USPLAT_OMP_SPIN, default 30000)``."""
    values = ", ".join(f"{k}={os.environ[k]}" if k in os.environ else f"{k} unset"
                       for k in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY"))
    return f"{values}: {outcome}"


# ---- how many threads ----------------------------------------------------------------------

THREADS_ENV_VAR = "USPLAT_THREADS"
#: How long ``busy_cores`` samples the CPUs' counters (seconds), and how long ``choose``
#: reuses a sample (a test suite or a demo builds many runs in one process).
SAMPLE_S = 0.3
REUSE_S = 60.0
_last: tuple[float, float | None] | None = None  # (time.monotonic(), busy_cores())
#: Fields of a ``/proc/stat`` cpu line that count as busy (of: user nice system idle iowait irq
#: softirq steal guest guest_nice; guest time is already inside user): steal is time the
#: hypervisor gave to someone else, as unavailable to us as another process's.
_BUSY = (0, 1, 2, 5, 6, 7)


@dataclass(frozen=True)
class Choice:
    threads: int
    allowed: int  # cores this process may run on
    busy: float | None  # cores other processes kept busy during the sample (None: not sampled)
    why: str

    def line(self) -> str:
        """One log line, e.g. ``threads: 1 (2 cores allowed, 1.0 busy with other processes;
        USPLAT_THREADS=auto)``."""
        return f"threads: {self.threads} ({self.why})"


def affinity_cores() -> int:
    """The CPUs this process may run on (its affinity; ``os.cpu_count()`` where unknown)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def allowed_cores() -> int:
    """Cores this process may use: its CPU affinity, capped by a cgroup v2 CPU quota
    (``cpu.max``, e.g. a container's ``--cpus``), at least 1."""
    n = affinity_cores()
    quota = cgroup_quota()
    if quota is not None:
        n = min(n, max(1, math.ceil(quota - 1e-6)))
    return max(1, n)


def cgroup_quota(root: Path = Path("/sys/fs/cgroup")) -> float | None:
    """The cgroup v2 CPU quota in cores (``cpu.max``: ``quota period``), or None (unlimited
    or not readable)."""
    try:
        quota, period = (root / "cpu.max").read_text().split()[:2]
    except (OSError, ValueError):
        return None
    if quota == "max":
        return None
    try:
        return int(quota) / int(period)
    except (ValueError, ZeroDivisionError):
        return None


def _cpu_counters(cpus: set[int], stat: Path) -> tuple[int, int]:
    """(busy, total) jiffies summed over ``cpus`` from ``/proc/stat``."""
    busy = total = 0
    for line in stat.read_text().splitlines():
        name, *fields = line.split()
        if not name.startswith("cpu") or name == "cpu":
            continue
        if not name[3:].isdigit() or int(name[3:]) not in cpus:
            continue
        values = [int(v) for v in fields[:8]]
        busy += sum(values[i] for i in _BUSY if i < len(values))
        total += sum(values)
    return busy, total


def busy_cores(seconds: float = SAMPLE_S, stat: Path = Path("/proc/stat")) -> float | None:
    """Cores that *other* processes kept busy over ``seconds``, on the CPUs this process may
    use: their busy share from ``/proc/stat`` times their number, less this process's own
    CPU time over the sample. None where ``/proc/stat`` cannot be read (not Linux)."""
    try:
        cpus = os.sched_getaffinity(0)
        b0, t0 = _cpu_counters(cpus, stat)
        own0, w0 = time.process_time(), time.perf_counter()
        time.sleep(seconds)
        b1, t1 = _cpu_counters(cpus, stat)
        own = (time.process_time() - own0) / max(time.perf_counter() - w0, 1e-9)
    except (AttributeError, OSError, ValueError):
        return None
    if t1 <= t0:
        return None
    return max(0.0, len(cpus) * (b1 - b0) / (t1 - t0) - own)


def recent_busy_cores() -> float | None:
    """``busy_cores()``, sampled at most once every ``REUSE_S`` seconds in a process."""
    global _last
    if _last is None or time.monotonic() - _last[0] > REUSE_S:
        _last = (time.monotonic(), busy_cores())
    return _last[1]


def choose(setting: str | None = None, measure=recent_busy_cores) -> Choice:
    """The thread count for a run: ``setting`` (default ``$USPLAT_THREADS``, else ``auto``):
    a number, ``all``, or ``auto`` (allowed cores less busy ones, rounded, at least 1).
    A ``ValueError`` names the variable for anything else."""
    raw = setting if setting is not None else os.environ.get(THREADS_ENV_VAR, "auto")
    value = str(raw).strip().lower()
    allowed = allowed_cores()
    if value.isdigit() and int(value) >= 1:
        cpus = os.cpu_count() or 1
        if int(value) > cpus:  # more threads than CPUs only time-slice (thousands fail)
            raise ValueError(f"{THREADS_ENV_VAR}={raw} is more than this machine's {cpus} "
                             f"CPUs: give at most {cpus}, 'all' or 'auto'")
        return Choice(int(value), allowed, None, f"{THREADS_ENV_VAR}={value}")
    if value == "all":
        return Choice(allowed, allowed, None, f"{allowed} core(s) allowed; {THREADS_ENV_VAR}=all")
    if value not in ("auto", ""):
        raise ValueError(f"{THREADS_ENV_VAR} must be a number >= 1, 'all' or 'auto', got {raw!r}")
    busy = measure() if allowed > 1 else None
    if busy is None:
        return Choice(allowed, allowed, None, f"{allowed} core(s) allowed, load not sampled"
                      if allowed > 1 else "1 core allowed")
    # the cores others leave free on the CPUs we may run on, at most our allowance: under a
    # quota (a container's --cpus 2 on a 64-core host) other tenants' load on the other CPUs
    # takes nothing from us
    free = min(allowed, affinity_cores() - busy)
    threads = max(1, min(allowed, math.floor(free + 0.5)))
    return Choice(threads, allowed, busy, f"{allowed} core(s) allowed, {busy:.1f} busy with "
                                          f"other processes; {THREADS_ENV_VAR}=auto")
