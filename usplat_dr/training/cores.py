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

No third-party imports.
"""

import os
import subprocess
import sys

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


def wanted(setting: bool | None, threads: int, device: str) -> bool:
    """Whether to keep the cores awake. ``setting``: True / False decide; ``None`` (auto) means
    on for a CPU job on Linux whose ``threads`` (> 1) cover every core it may use, that is a
    job that owns the machine and whose idle moments are only waits between its threads."""
    if setting is not None:
        return bool(setting)
    return (device == "cpu" and sys.platform.startswith("linux") and threads > 1
            and threads >= len(available_cpus()))


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
