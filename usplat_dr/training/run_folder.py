"""What a training run holds while it trains: its folder (``run_folder_lock``: a second run
there stops at start-up, naming the first's pid; the temporary files of writes a killed run left
are removed on taking it), SIGINT/SIGTERM (``signals_caught``) and, where wanted, the cores kept
awake (``cores_awake``)."""

import contextlib
import fcntl
import logging
import os
import signal
from collections.abc import Iterator
from pathlib import Path

import torch

from usplat_dr.config import ConfigError
from usplat_dr.io.atomic import ATOMIC_TEMPORARY
from usplat_dr.training import cores as _cores

log = logging.getLogger(__name__)

#: The lock file of a run folder, held with ``fcntl.flock`` while a run trains there. The
#: kernel releases a flock when its process ends, however it ends: a SIGKILLed run leaves no
#: stale lock. The file holds the pid of its holder (for the message of a refused run).
LOCK_NAME = ".usplat-train.lock"
_held: dict[Path, list] = {}  # folder -> [lock's file descriptor, depth]: re-entrant


def _take_lock(folder: Path) -> int:
    """Create ``folder`` and take its lock (a file descriptor); a ``ConfigError`` naming the
    folder when it is a file, or another process holds the lock (naming its pid)."""
    if folder.exists() and not folder.is_dir():
        raise ConfigError(f"output_dir={folder} is an existing file, not a folder: choose "
                          f"another output_dir=... (or move the file away)")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise ConfigError(f"output_dir={folder}: a part of this path is a file, not a folder: "
                          f"choose another output_dir=...") from None
    fd = os.open(folder / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        pid = os.read(fd, 32).decode(errors="replace").strip()
        os.close(fd)
        who = f"pid {pid}" if pid.isdigit() else "pid unknown"
        raise ConfigError(f"output_dir={folder} is in use by another usplat train ({who}): "
                          f"wait for it to end or stop it, or choose another "
                          f"output_dir=...") from None
    try:  # the pid only informs a refused run's message: a failed write changes nothing
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
    except OSError:
        pass
    return fd


def remove_temporary_files(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporary files of killed atomic writes (``ATOMIC_TEMPORARY``) under
    ``folder``, recursively (symbolic links to folders are not followed); returns them. Call
    it only while holding the folder's lock: a running run's write in flight looks the same."""
    removed = []
    for parent, _, names in os.walk(folder):
        for name in names:
            if ATOMIC_TEMPORARY.fullmatch(name):
                path = Path(parent) / name
                path.unlink(missing_ok=True)
                removed.append(path)
    if removed:
        log.info("removed %d temporary file(s) of writes a killed run left in %s: %s",
                 len(removed), folder, ", ".join(str(p) for p in removed[:3]))
    return removed


@contextlib.contextmanager
def run_folder_lock(folder: str | os.PathLike) -> Iterator[Path]:
    """Hold the run folder ``folder`` (created if needed) for the block: another process
    asking for it meanwhile gets a ``ConfigError`` naming the folder and this process's pid.
    Re-entrant within a process. Taking it removes the temporary files killed writes left
    (``remove_temporary_files``). Also a ``ConfigError`` when ``folder`` is a file."""
    folder, key = Path(folder), Path(folder).resolve()
    first = key not in _held
    if first:
        _held[key] = [_take_lock(folder), 0]
    entry = _held[key]
    entry[1] += 1
    try:
        if first:
            remove_temporary_files(folder)
        yield folder
    finally:
        entry[1] -= 1
        if entry[1] == 0:
            del _held[key]
            os.close(entry[0])


@contextlib.contextmanager
def signals_caught(handler) -> Iterator[None]:
    """SIGINT and SIGTERM call ``handler(signum, frame)`` in the block; the handlers from
    before come back after it."""
    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def cores_awake(setting, device: torch.device) -> contextlib.AbstractContextManager:
    """Idle-priority spinners (``CoreKeeper``) for the block where ``keep_cores_awake``
    (``setting``) wants them (``usplat_dr.training.cores.decide``: the setting, or a probe of
    how fast idle cores wake), else a context that does nothing; logs which and why."""
    on, why = _cores.decide(setting, torch.get_num_threads(), device.type)
    log.info("%s", _cores.log_line(on, why))
    if on:
        return _cores.CoreKeeper()
    return contextlib.nullcontext()
