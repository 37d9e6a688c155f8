"""Atomic file writes: a killed process leaves either the old file or the new one, never half."""

import contextlib
import json
import os
import re
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file beside ``path``; on success it is fsynced and renamed over ``path``.

    Examples:
        >>> import tempfile, pathlib
        >>> p = pathlib.Path(tempfile.mkdtemp()) / "a.txt"
        >>> with atomic_open(p, "w") as f:
        ...     _ = f.write("hello")
        >>> p.read_text()
        'hello'
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"mode must be 'w' or 'wb', got {mode!r}")
    path = Path(path)
    refuse_special(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file normal permissions
    try:
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


#: The temporary files of ``atomic_open``: ``tempfile.mkstemp``'s ``.<name>.<8 random
#: characters>.tmp`` beside the target, left behind by a killed write.
ATOMIC_TEMPORARY = re.compile(r"\..+\.[a-z0-9_]{8}\.tmp")


def remove_temporaries_of(path: str | os.PathLike) -> list[Path]:
    """Remove the temporary files that killed ``atomic_open`` writes of ``path`` left beside
    it; returns them. (Only for a file no other process is writing.)

    Examples:
        >>> import tempfile, pathlib
        >>> folder = pathlib.Path(tempfile.mkdtemp())
        >>> _ = (folder / ".a.json.k3j_9x0q.tmp").write_text("{")
        >>> [p.name for p in remove_temporaries_of(folder / "a.json")]
        ['.a.json.k3j_9x0q.tmp']
    """
    path = Path(path)
    prefix = f".{path.name}."
    if not path.parent.is_dir():
        return []
    found = [p for p in path.parent.iterdir()
             if p.name.startswith(prefix) and ATOMIC_TEMPORARY.fullmatch(p.name)
             and len(p.name) == len(prefix) + len("12345678.tmp") and p.is_file()]
    for p in found:
        p.unlink(missing_ok=True)
    return found


def refuse_special(path: Path) -> None:
    """Raise ``ValueError`` when ``path`` exists and is not a regular file (or a link to one):
    a device, FIFO, socket or folder is never renamed over (as root, ``os.replace`` would
    replace ``/dev/null`` itself)."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return
    except OSError as e:
        raise ValueError(f"{path}: cannot be written ({e.strerror}); name a new file") from None
    if not stat.S_ISREG(st.st_mode):
        kind = "folder" if stat.S_ISDIR(st.st_mode) else "special file (device, FIFO or socket)"
        raise ValueError(f"{path} exists and is a {kind}, not a regular file: name a new file "
                         "to write to")


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 1) -> Path:
    """Write ``obj`` as JSON, atomically."""
    with atomic_open(path, "w") as f:
        json.dump(obj, f, indent=indent)
        f.write("\n")
    return Path(path)


def torch_save(obj: Any, path: str | os.PathLike) -> Path:
    """``torch.save`` to ``path``, atomically."""
    import torch  # only here: the JSON and text writers do not load it (start-up time)

    with atomic_open(path, "wb") as f:
        sink = _WriteErrors(f)
        try:
            torch.save(obj, sink)
        except RuntimeError:
            # torch's zip writer reports a failed write (a full disk) as a RuntimeError about
            # the stream position; the OSError itself says what to fix
            if sink.error is not None:
                raise sink.error from None
            raise
    return Path(path)


class _WriteErrors:
    """A binary file that keeps the ``OSError`` of a failed write (``error``)."""

    def __init__(self, f: IO[bytes]):
        self.f, self.error = f, None

    def write(self, data) -> int:
        try:
            return self.f.write(data)
        except OSError as e:
            self.error = e
            raise

    def flush(self) -> None:
        self.f.flush()


def save_figure(fig, path: str | os.PathLike) -> Path:
    """A matplotlib figure written atomically as a PNG at 110 dpi (the project's charts),
    its folder made, the figure closed; the path."""
    import matplotlib.pyplot as plt  # only here: the caller has matplotlib

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=110)
    plt.close(fig)
    return path
