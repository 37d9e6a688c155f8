"""The one door for files a user names and the files those name: a regular file of bounded
size, a path kept inside the folder whose file names it, and images decoded as PNG or JPEG
only, their size checked before any pixel is decoded and any resize bounded.

Every refusal is a ``ValueError`` (or its ``FileNotFoundError`` kin, ``OSError``) whose
message names the file and what to do, so that the commands print one line and exit 2.
``tests/test_layering.py`` fails if another module of the library opens images itself.

Examples:
    >>> inside(Path("/data/scene"), "images/frame_000.png", "image").as_posix()
    '/data/scene/images/frame_000.png'
    >>> inside(Path("/data/scene"), "../../etc/passwd", "image")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: image '../../etc/passwd' leaves /data/scene: data files may name only ...
"""

import hashlib
import io
import os
import stat
from pathlib import Path

import numpy as np
from PIL import Image

#: The formats images are decoded as (the field's: pixelSplat's chunks hold JPEG, ours PNG).
#: Pillow would otherwise try every format it knows, EPS among them, which runs Ghostscript.
IMAGE_FORMATS = ("PNG", "JPEG")
#: Pixels one image may claim (8192 x 8192): a larger header is a corrupt or hostile file.
MAX_IMAGE_PIXELS = 8192 * 8192
#: Bytes one image file may hold (a 8192 x 8192 PNG of noise is about 200 MB).
MAX_IMAGE_BYTES = 256 * 2**20
#: Bytes a camera or scene description file (COLMAP, transforms.json, PLY) may hold by default.
MAX_DATA_BYTES = 2**30
_MAGIC = (b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff")


def regular_file(path: str | os.PathLike, what: str, max_bytes: int = MAX_DATA_BYTES) -> Path:
    """``path`` when it is a regular file (a FIFO, a device or a folder is refused: reading
    them never ends or means nothing) of at most ``max_bytes`` bytes; ``what`` names it in
    the error."""
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} {path} does not exist") from None
    except OSError as e:
        raise ValueError(f"{what} {path} cannot be read ({e.strerror or e})") from None
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"{what} {path} is not a regular file (a folder, FIFO or device): "
                         f"name a file")
    if st.st_size > max_bytes:
        raise ValueError(f"{what} {path} holds {st.st_size:,} bytes, more than the "
                         f"{max_bytes:,} such a file can need: a damaged or wrong file")
    return path


def read_bytes(path: str | os.PathLike, what: str, max_bytes: int = MAX_DATA_BYTES) -> bytes:
    """The bytes of ``regular_file(path, what, max_bytes)``, read with the bound kept even if
    the file grows meanwhile."""
    path = regular_file(path, what, max_bytes)
    blocks, total = [], 0
    with open(path, "rb") as f:
        # in blocks of what the file holds (64 KiB to READ_BLOCK): ``f.read(max_bytes)`` would
        # ask for the maximum at once, which a memory limit refuses for a 10 kB file
        expected = os.fstat(f.fileno()).st_size
        while block := f.read(max(1 << 16, min(expected - total + 1, READ_BLOCK))):
            total += len(block)
            if total > max_bytes:
                raise ValueError(f"{what} {path} grew past {max_bytes:,} bytes while being "
                                 f"read")
            blocks.append(block)
    return b"".join(blocks)


#: The most ``read_bytes`` asks of a file at once.
READ_BLOCK = 16 * 2**20


def sha256(path: str | os.PathLike, what: str, max_bytes: int = MAX_DATA_BYTES,
           digest=None) -> str:
    """The SHA-256 of ``regular_file(path, what, max_bytes)``'s bytes, read in 1 MiB blocks
    and never past ``max_bytes``; with ``digest`` (a ``hashlib`` object), the bytes update it
    (its hex digest is returned)."""
    path = regular_file(path, what, max_bytes)
    digest = digest if digest is not None else hashlib.sha256()
    left = max_bytes
    with open(path, "rb") as f:
        while block := f.read(min(1 << 20, left + 1)):
            left -= len(block)
            if left < 0:
                raise ValueError(f"{what} {path} grew past {max_bytes:,} bytes while being read")
            digest.update(block)
    return digest.hexdigest()


def inside(folder: Path, name: object, what: str) -> Path:
    """``folder / name`` where ``name`` (read from a data file in ``folder``) stays inside
    ``folder``: an absolute name or one whose ``..`` leave it is refused. Symbolic links
    inside the folder are the user's own and are followed."""
    if not isinstance(name, str) or not name or "\x00" in name:
        raise ValueError(f"{what} {name!r} is not a file name")
    candidate = Path(name)
    if candidate.is_absolute() or candidate.drive:
        raise ValueError(f"{what} {name!r} is an absolute path: data files may name only "
                         f"files inside their own folder ({folder})")
    depth = 0
    for part in candidate.parts:
        depth += -1 if part == ".." else (0 if part == "." else 1)
        if depth < 0:
            raise ValueError(f"{what} {name!r} leaves {folder}: data files may name only "
                             f"files inside their own folder")
    return folder / candidate


def open_image(data: bytes, what: str) -> Image.Image:
    """A lazily decoded PIL image of ``data`` (PNG or JPEG bytes), its claimed size checked
    against ``MAX_IMAGE_PIXELS`` before any pixel is decoded. Other formats are refused by
    their first bytes (no format plugin sees them)."""
    if not data.startswith(_MAGIC):
        raise ValueError(f"{what} cannot be decoded: not a PNG or JPEG file (its first bytes "
                         f"are {data[:8]!r}): convert it to PNG or JPEG")
    try:
        im = Image.open(io.BytesIO(data), formats=IMAGE_FORMATS)
    except Exception as e:  # noqa: BLE001  (Pillow's plugins raise many kinds on damaged bytes)
        raise ValueError(f"{what} cannot be decoded ({type(e).__name__}: {e})") from None
    w, h = im.size
    if w < 1 or h < 1 or w * h > MAX_IMAGE_PIXELS:
        im.close()
        raise ValueError(f"{what} claims {w}x{h} pixels (at most {MAX_IMAGE_PIXELS:,}): a "
                         f"corrupt header, or an image to downscale first")
    return im


def rgb8(im: Image.Image) -> np.ndarray:
    """[H, W, 3] uint8 of an image from ``open_image``, decoded now (a damaged body is a
    ``ValueError``). Pillow's ``convert("RGB")`` clips 16-bit grey ("I;16", or "I" from older
    Pillow) at 255 instead of scaling it: that is scaled by 255 / 65535 and rounded."""
    try:
        if im.mode.startswith("I;16") or im.mode == "I":
            grey = np.clip(np.asarray(im).astype(np.float64), 0, 65535) * (255.0 / 65535.0)
            return np.repeat(np.rint(grey).astype(np.uint8)[..., None], 3, axis=-1)
        return np.asarray(im.convert("RGB"))
    except Exception as e:  # noqa: BLE001  (truncated or damaged pixel data, any plugin)
        raise ValueError(f"an image cannot be decoded ({type(e).__name__}: {e})") from None


def read_image(path: str | os.PathLike, what: str = "image") -> np.ndarray:
    """[H, W, 3] uint8 RGB of the PNG or JPEG file ``path`` (``regular_file``, then
    ``open_image`` and ``rgb8``); ``what`` names it in errors."""
    path = Path(path)
    with open_image(read_bytes(path, what, MAX_IMAGE_BYTES), f"{what} {path}") as im:
        try:
            return rgb8(im)
        except ValueError as e:
            raise ValueError(f"{what} {path}: {e}") from None


def check_resize(shape: tuple[int, int], new_shape: tuple[int, int], what: str) -> None:
    """Refuse a resize of an image of ``shape`` (H, W) to ``new_shape`` with more than
    ``MAX_IMAGE_PIXELS`` pixels (a 1 x 4,000,000 image scaled to cover 64 x 64 would ask for
    64 x 256M)."""
    h, w = new_shape
    if h * w > MAX_IMAGE_PIXELS:
        raise ValueError(f"{what}: resizing its {shape[1]}x{shape[0]} pixels to {w}x{h} would "
                         f"make more than {MAX_IMAGE_PIXELS:,}: its aspect ratio is too far "
                         f"from the target's; crop it first")
