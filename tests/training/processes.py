"""Helpers of the tests that run ``usplat train`` as a real process and stop it: its
environment, a file's identity, polling for progress, SIGKILL."""

import os
import signal
import subprocess
import time
from pathlib import Path

REPO = Path(__file__).parents[2]


def environment() -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}


def stamp(path: Path):
    """The file's identity and size (an atomic replace makes a new inode), or None."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    return st.st_ino, st.st_size, st.st_mtime_ns


def wait_for(predicate, proc: subprocess.Popen, timeout: float = 120.0) -> bool:
    """Poll ``predicate`` every millisecond (a kill can then land right after a write) until
    it holds (True) or ``proc`` ends (False)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.001)
    raise TimeoutError("usplat train made no progress")


def stop(proc: subprocess.Popen) -> str:
    """SIGKILL ``proc`` (if still running); its stderr."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGKILL)
    return proc.communicate(timeout=60)[1].decode()
