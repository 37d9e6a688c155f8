"""Keep a machine's cores from halting while a multi-threaded CPU job runs on all of them.

On virtual machines whose guest halts an idle vCPU at once (Firecracker with
``haltpoll.guest_halt_poll_ns=0``, as ours), waking that vCPU again goes through the host and
took 1-8 ms here, against microseconds on bare metal. A training step at two threads lets the
second core idle dozens of times: whenever work passes between torch's OpenMP pool and Dr.Jit's
thread pool, and in the Python between operations. Each torch operation large enough to run
in parallel then waits for its second thread: an element-wise product of 49,000 floats took
1.5-4.5 ms right after a rasteriser call instead of 0.08 ms. With the cores kept awake, a
two-thread step of the tiny preset took 0.86-1.17x as long in 13 alternated rounds (median
0.92x; train/bench/README.md, "Halting vCPUs").

``CoreKeeper`` starts one process per core that spins at the lowest scheduling priority
(``SCHED_IDLE``): it runs only when nothing else wants that core, and the kernel preempts it at
once for any other thread, so the vCPU never halts and a waking thread starts without the
host's delay. It spends only cycles the job leaves idle, and it exits with its parent (even a
killed one). Linux only; elsewhere, or where ``SCHED_IDLE`` is refused, it does nothing.

Elsewhere it only burns power: on bare metal or a VM whose idle vCPUs poll, a core wakes in
microseconds. So ``decide`` turns it on only where a short probe at start
(``probe_wake_latency``, ~0.3 s) finds idle cores slow to wake.

No third-party imports.
"""

import os
import statistics
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

#: What each keeper process runs: idle priority, pinned to its core, spinning until its
#: parent goes away (checked every ~1 ms of spinning).
_SPIN = """
import os, sys
parent, cpu = int(sys.argv[1]), int(sys.argv[2])
try:
    os.sched_setaffinity(0, {cpu})
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
except (AttributeError, OSError):
    sys.exit(0)
sys.stdout.write("ready\\n")
sys.stdout.flush()
while os.getppid() == parent:
    for _ in range(20000):
        pass
"""


def available_cpus() -> list[int]:
    """The CPUs this process may run on (its affinity), or ``range(os.cpu_count())``."""
    try:
        return sorted(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return list(range(os.cpu_count() or 1))


#: The probe's two processes: the sleeper on ``b`` blocks in ``read()``; the pinger on ``a``,
#: after an idle gap, takes the time and writes a byte; the sleeper takes the time as it wakes
#: and sends it back. CLOCK_MONOTONIC is one clock for both processes, so the difference is
#: one wake-up of an idle core (plus ~2 us of Python), the wait a thread pool's worker sees.
_PROBE = """
import os, sys, time
a, b, rounds = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
gaps = [float(g) / 1000 for g in sys.argv[4].split(",")]
ping_r, ping_w = os.pipe()
pong_r, pong_w = os.pipe()
pid = os.fork()
if pid == 0:
    try:
        os.close(ping_w)
        os.close(pong_r)
        os.sched_setaffinity(0, {b})
        os.write(pong_w, b"r")
        while os.read(ping_r, 1):
            woke = time.monotonic_ns()
            os.write(pong_w, woke.to_bytes(8, "little"))
    finally:
        os._exit(0)
os.close(ping_r)
os.close(pong_w)
os.sched_setaffinity(0, {a})
if os.read(pong_r, 1) != b"r":
    sys.exit(1)
samples = []
for i in range(rounds):
    time.sleep(gaps[i % len(gaps)])
    sent = time.monotonic_ns()
    os.write(ping_w, b"p")
    samples.append(int.from_bytes(os.read(pong_r, 8), "little") - sent)
os.close(ping_w)
os.waitpid(pid, 0)
print(" ".join(map(str, samples)))
"""

#: Idle gaps before each wake-up (ms, cycled): longer than a KVM guest's and its host's halt
#: polling (``haltpoll.guest_halt_poll_ns`` and ``kvm.halt_poll_ns``, 200 us by default), so a
#: vCPU that halts when idle has halted; as short as a training step's idle moments.
PROBE_GAPS_MS = (1.0, 2.0, 3.0)
PROBE_ROUNDS = 100

#: Above this median wake-up the keeper is on. Bare metal in shallow idle states wakes a
#: blocked thread in ~5-20 us (plus ~2 us of the probe's Python); a KVM guest whose vCPU halted
#: takes ~50-200 us, and ours (Firecracker, ``haltpoll.guest_halt_poll_ns=0``) 1-8 ms. The
#: keeper's gain was measured only at such millisecond wakes (0.92x step time); a step waits
#: dozens of times, so at 60 us the waits cost ~2 % of a 150 ms step at most, less than the
#: host's swings: below it the spinners' power is not worth spending.
WAKE_THRESHOLD_US = 60.0


@dataclass(frozen=True)
class WakeProbe:
    """What ``probe_wake_latency`` measured: the median wake-up of an idle core (us), over
    ``rounds`` wake-ups of ``cpus[1]`` from ``cpus[0]``, and the 10th-90th percentiles."""

    median_us: float
    rounds: int
    cpus: tuple[int, int]
    low_us: float
    high_us: float

    def __str__(self) -> str:
        return f"idle cores woke in {self.median_us:.0f} us (median of {self.rounds})"


def probe_wake_latency(cpus: list[int] | None = None, rounds: int = PROBE_ROUNDS,
                       gaps_ms: tuple[float, ...] = PROBE_GAPS_MS,
                       timeout: float = 10.0) -> WakeProbe | None:
    """How long an idle core takes to wake a thread blocked on it: two processes pinned to
    the first two of ``cpus`` (default: this process's) ping-pong through pipes ``rounds``
    times, each after an idle gap of ``gaps_ms``; ~0.3 s with the defaults. None where it
    cannot run (not Linux, one CPU, affinity refused, ``timeout`` seconds passed).

    Examples:
        >>> probe = probe_wake_latency(rounds=5)
        >>> probe is None or probe.median_us > 0
        True
    """
    cpus = available_cpus() if cpus is None else list(cpus)
    if len(cpus) < 2 or not sys.platform.startswith("linux"):
        return None
    try:
        res = subprocess.run([sys.executable, "-I", "-S", "-c", _PROBE, str(cpus[0]),
                              str(cpus[1]), str(rounds), ",".join(map(str, gaps_ms))],
                             stdin=subprocess.DEVNULL, capture_output=True, text=True,
                             timeout=timeout, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    samples = sorted(int(s) / 1000 for s in res.stdout.split())
    if res.returncode or len(samples) != rounds:
        return None
    return WakeProbe(statistics.median(samples), rounds, (cpus[0], cpus[1]),
                     samples[len(samples) // 10], samples[len(samples) * 9 // 10])


def hypervisor() -> bool | None:
    """Whether /proc/cpuinfo's flags include ``hypervisor`` (x86 guests), None where it has
    no flags line (other CPUs, not Linux)."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return None
    flags = next((line for line in lines if line.startswith("flags")), None)
    return None if flags is None else "hypervisor" in flags.split()


def cpuidle_driver() -> str | None:
    """The kernel's cpuidle driver (``haltpoll`` in a KVM guest that uses it), or None."""
    try:
        return Path("/sys/devices/system/cpu/cpuidle/current_driver").read_text().strip()
    except OSError:
        return None


def decide(setting: bool | str | None, threads: int, device: str,
           measure: Callable[[], WakeProbe | None] | None = None) -> tuple[bool, str]:
    """Whether to keep the cores awake, and why (for the log). ``setting``: True / False
    decide; ``"auto"`` (or None) means on for a CPU job on Linux whose ``threads`` (> 1) cover
    every core it may use (a job that owns the machine, whose idle moments are only waits
    between its threads) on a virtual machine whose idle cores wake slower than
    ``WAKE_THRESHOLD_US`` (``measure``, default ``probe_wake_latency``)."""
    if isinstance(setting, bool):
        return setting, f"keep_cores_awake={str(setting).lower()}"
    if device != "cpu":
        return False, f"device={device}: the job does not wait on the CPU's cores"
    if not sys.platform.startswith("linux"):
        return False, f"{sys.platform}: SCHED_IDLE spinners are Linux's"
    cores = len(available_cpus())
    if threads <= 1:
        return False, "one thread: no waits between threads"
    if threads < cores:
        return False, f"{threads} threads on {cores} cores: other work may use the rest"
    probe = (measure or probe_wake_latency)()
    if probe is None:
        return False, "the wake-up probe could not run here"
    if probe.median_us <= WAKE_THRESHOLD_US:
        return False, f"{probe}, below {WAKE_THRESHOLD_US:.0f} us"
    slow = f"{probe}, above {WAKE_THRESHOLD_US:.0f} us"
    if hypervisor() is False:
        return False, (f"{slow}, but on bare metal (no hypervisor flag in /proc/cpuinfo): "
                       "the CPU's deep idle states, which save power")
    driver = cpuidle_driver()
    return True, (f"{slow}: this machine halts idle vCPUs"
                  + (f" (cpuidle driver {driver})" if driver else ""))


def log_line(on: bool, why: str) -> str:
    """The line ``usplat train`` logs: ``core keeper on: <why>`` / ``core keeper off: ...``."""
    return f"core keeper {'on' if on else 'off'}: {why}"


def wanted(setting: bool | str | None, threads: int, device: str) -> bool:
    """``decide``'s answer alone."""
    return decide(setting, threads, device)[0]


class CoreKeeper:
    """Idle-priority spinners on ``cpus`` (default: every CPU this process may use) while
    started.

        with CoreKeeper():
            trainer.fit()
    """

    def __init__(self, cpus: list[int] | None = None):
        self.cpus = list(available_cpus() if cpus is None else cpus)
        self.procs: list[subprocess.Popen] = []  # empty where SCHED_IDLE was refused

    def start(self) -> "CoreKeeper":
        if self.procs or not sys.platform.startswith("linux"):
            return self
        for cpu in self.cpus:
            p = subprocess.Popen([sys.executable, "-I", "-S", "-c", _SPIN, str(os.getpid()),
                                  str(cpu)], stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                 stderr=subprocess.DEVNULL)
            # "ready" once it is idle-priority and pinned; nothing if it was refused (it exited)
            if p.stdout.readline().strip() == b"ready":
                self.procs.append(p)
            else:
                p.wait()
                p.stdout.close()
        return self

    def stop(self) -> None:
        for p in self.procs:
            p.kill()
        for p in self.procs:
            p.wait()
            p.stdout.close()
        self.procs = []

    def __enter__(self) -> "CoreKeeper":  # noqa: PYI034 (typing.Self needs Python 3.11)
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
