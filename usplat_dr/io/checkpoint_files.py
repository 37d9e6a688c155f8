"""Reading ``torch.save`` files without running their code.

``torch.load(weights_only=True)`` rebuilds tensors and plain Python data only; a file that
also pickles other objects (a callable, a class instance) is refused, because unpickling them
can execute arbitrary code. Full unpickling happens only when the caller opts in
(``trust=True``) for a file it trusts.
"""

import os
import pickle
import stat
import zipfile
from pathlib import Path

import torch


class UntrustedCheckpointError(ValueError):
    """A file that ``torch.load(weights_only=True)`` refuses: it holds pickled objects beyond
    tensors and plain data, which could run code when loaded."""


def check_torch_archive(path: Path, what: str) -> None:
    """``ValueError`` unless ``path`` is a regular file whose zip records (when it is a zip:
    ``torch.save``'s format) are all stored uncompressed. ``torch.save`` never compresses, and
    ``torch.load`` inflates a deflated record in full before any check: a 4 MB file could
    unpack to 4 GB. A FIFO or device would block or never end: refused too."""
    try:
        mode = os.stat(path).st_mode
    except OSError as e:
        raise ValueError(f"{what} {str(path)!r} cannot be read ({e.strerror})") from None
    if not stat.S_ISREG(mode):
        raise ValueError(f"{what} {str(path)!r} is not a regular file (a FIFO, device or "
                         "folder)")
    try:
        with zipfile.ZipFile(path) as z:
            packed = [i.filename for i in z.infolist() if i.compress_type != zipfile.ZIP_STORED]
    except (zipfile.BadZipFile, OSError, ValueError, EOFError):
        return  # not a zip (torch's legacy format, or damage torch.load reports itself)
    if packed:
        raise ValueError(f"{what} {str(path)!r} holds compressed records ({packed[0]!r}, "
                         f"{len(packed)} in all), which torch.save never writes: refused "
                         "(re-save it with torch.save)")


def load_torch_file(path: str | os.PathLike, what: str = "checkpoint", map_location="cpu",
                    trust: bool = False, trust_hint: str = "trust_checkpoint=True"):
    """``torch.load`` ``path`` safely (``weights_only=True``); ``trust=True`` allows full
    unpickling. Errors name ``what``, the file and, for refused files, the opt-in
    (``trust_hint``: the argument or flag that sets ``trust``)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{what} {str(path)!r} does not exist")
    check_torch_archive(path, what)
    if trust:
        return torch.load(path, map_location=map_location, weights_only=False)
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        text = str(e)
        lines = [line.strip() for line in text.splitlines() if "GLOBAL" in line.upper()
                 and "global" in line.lower() and ("unsupported" in line.lower())]
        if lines:  # torch names the object it refused, e.g. "unsupported GLOBAL posix.system"
            detail = lines[0]
            raise UntrustedCheckpointError(
                f"{what} {str(path)!r} holds pickled objects beyond tensors and plain data "
                f"({detail[:200]}), which could run code when loaded: refused. If you trust "
                f"the file, pass {trust_hint}") from None
        reason = next((line.strip() for line in text.splitlines() if "load key" in line),
                      "not a pickle")
        raise ValueError(f"{what} {str(path)!r} is not a file written by torch.save "
                         f"({reason[:200]})") from None
    # anything else torch.load raises on a damaged file (RuntimeError, EOFError, BadZipFile,
    # OSError; KeyError or UnicodeDecodeError from a corrupt pickle) means "unreadable"
    except Exception as e:  # noqa: BLE001 (any decoder error: see above)
        raise ValueError(f"{what} {str(path)!r} is not a file written by torch.save, or it "
                         f"is truncated ({type(e).__name__}: {str(e)[:200]})") from None
