"""The pixelSplat chunk format, read and written exactly (docs/field_protocol.md,
"Data").

A dataset root holds one folder per stage (``train``, ``test``); each holds ``NNNNNN.torch``
chunks and ``index.json`` (scene key -> chunk file name relative to the stage folder). A chunk
is a ``torch.save``d list of scene dicts:

- ``key`` (str), ``url`` (str), ``timestamps`` (int64 [V]),
- ``cameras`` (float32 [V, 18]): fx, fy, cx, cy normalised by the image size, two unused
  floats, then the world-to-camera 3x4 matrix row-major (OpenCV axes),
- ``images``: V uint8 1-D tensors holding encoded JPEG/PNG bytes.

Our synthetic sets add ``depths`` (float16 [V, H, W], camera-space z, +inf on a miss),
``near_far`` (float32 [2]), ``tags`` (list of str) and ``mitsuba`` (the scene description).
Readers ignore keys they do not know, so the official loaders read our sets too.

Chunks are loaded with ``torch.load(weights_only=True)``: data never executes code.
"""

import io
import json
import logging
import os
import stat
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Float, UInt8
from PIL import Image
from torch import Tensor

from usplat_dr.io import torch_save, write_json
from usplat_dr.io.checkpoint_files import check_torch_archive
from usplat_dr.io.user_files import IMAGE_FORMATS, MAX_IMAGE_PIXELS, open_image, read_bytes, rgb8

__all__ = ["IMAGE_FORMATS", "MAX_IMAGE_PIXELS"]  # (re-exported: the data layer's readers)

log = logging.getLogger(__name__)

STAGES = ("train", "test")


class BadSceneError(ValueError):
    """A scene that cannot be used (corrupt image, bad camera, malformed record)."""


class BadChunkError(ValueError):
    """A chunk file that cannot be read (truncated, not a list of scene dicts)."""


# ---- Cameras ----


def cameras_to_matrices(
    cameras: Float[Tensor, "view 18"],
) -> tuple[Float[Tensor, "view 4 4"], Float[Tensor, "view 3 3"]]:
    """Decode the 18-float camera rows into OpenCV camera-to-world matrices and normalised
    intrinsics (as pixelSplat's ``convert_poses``).

    Raises ``BadSceneError`` for non-finite values or a rotation that is not (close to) a
    rotation: a singular world-to-camera matrix cannot be inverted into a pose.

    Examples:
        >>> row = torch.tensor([[0.8, 0.9, 0.5, 0.5, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 2.0]])
        >>> c2w, k = cameras_to_matrices(row)
        >>> c2w[0, :3, 3].tolist(), k[0, 0, 0].item() == row[0, 0].item()
        ([0.0, 0.0, -2.0], True)
    """
    if cameras.ndim != 2 or cameras.shape[1] != 18:
        raise BadSceneError(f"cameras must have shape (V, 18), got {tuple(cameras.shape)}")
    cameras = cameras.float()
    if not torch.isfinite(cameras).all():
        raise BadSceneError("cameras contain NaN or Inf")
    v = cameras.shape[0]
    fx, fy, cx, cy = cameras[:, :4].T
    intrinsics = torch.zeros(v, 3, 3)
    intrinsics[:, 0, 0] = fx
    intrinsics[:, 1, 1] = fy
    intrinsics[:, 0, 2] = cx
    intrinsics[:, 1, 2] = cy
    intrinsics[:, 2, 2] = 1.0
    if (fx <= 0).any() or (fy <= 0).any():
        raise BadSceneError("cameras have a non-positive focal length")
    # Finite but absurd values overflow float32 in the model (squared distances, projected
    # positions): normalised intrinsics beyond 1e4 (a field of view under 0.006 degrees) and
    # positions beyond 1e6 scene units are a corrupt record, not a camera.
    if (cameras[:, :4].abs() > 1e4).any():
        raise BadSceneError(f"camera intrinsics beyond 1e4 (normalised by the image size): "
                            f"{cameras[:, :4].abs().max().item():.3g}")
    if (cameras[:, 6:].abs() > 1e6).any():
        raise BadSceneError(f"a camera pose entry beyond 1e6: "
                            f"{cameras[:, 6:].abs().max().item():.3g}")
    w2c = torch.eye(4).repeat(v, 1, 1)
    w2c[:, :3] = cameras[:, 6:].reshape(v, 3, 4)
    rot = w2c[:, :3, :3].double()
    # A proper rotation has det 1 and orthonormal rows; 1e-3 admits the rounding of poses
    # stored as float32 text (RealEstate10K metadata has 6-7 significant digits).
    det = torch.linalg.det(rot)
    err = (rot @ rot.transpose(-1, -2) - torch.eye(3, dtype=rot.dtype)).abs().amax(dim=(-1, -2))
    if (det.abs() < 1e-6).any():
        raise BadSceneError("a camera rotation is singular")
    if ((det - 1).abs() > 1e-3).any() or (err > 1e-3).any():
        raise BadSceneError(f"a camera rotation is not orthonormal (max error {err.max():.2g}, "
                            f"det {det[(det - 1).abs().argmax()]:.4g})")
    return torch.linalg.inv(w2c.double()).float(), intrinsics


def matrices_to_cameras(
    c2w: Float[Tensor, "view 4 4"], intrinsics: Float[Tensor, "view 3 3"]
) -> Float[Tensor, "view 18"]:
    """The inverse of ``cameras_to_matrices``: 18-float rows (world-to-camera, row-major)."""
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4):
        raise ValueError(f"c2w must have shape (V, 4, 4), got {tuple(c2w.shape)}")
    if intrinsics.shape != (c2w.shape[0], 3, 3):
        raise ValueError(f"intrinsics must have shape ({c2w.shape[0]}, 3, 3), "
                         f"got {tuple(intrinsics.shape)}")
    w2c = torch.linalg.inv(c2w.double()).float()
    k = intrinsics.float()
    head = torch.stack([k[:, 0, 0], k[:, 1, 1], k[:, 0, 2], k[:, 1, 2],
                        torch.zeros_like(k[:, 0, 0]), torch.zeros_like(k[:, 0, 0])], dim=-1)
    return torch.cat([head, w2c[:, :3].reshape(-1, 12)], dim=-1)


# ---- Images ----


def encode_image(image: UInt8[np.ndarray, "h w 3"], fmt: str = "png",
                 quality: int = 95) -> UInt8[Tensor, " nbytes"]:
    """Encode an [H, W, 3] uint8 image as PNG or JPEG bytes in a uint8 tensor (the chunk form)."""
    if fmt not in ("png", "jpeg"):
        raise ValueError(f"fmt must be 'png' or 'jpeg', got {fmt!r}")
    buf = io.BytesIO()
    # PNG at compress_level 6 without timestamps is byte-for-byte deterministic.
    kwargs = {"quality": quality} if fmt == "jpeg" else {"compress_level": 6}
    Image.fromarray(np.ascontiguousarray(image)).save(buf, format=fmt.upper(), **kwargs)
    return torch.frombuffer(bytearray(buf.getvalue()), dtype=torch.uint8)


def decode_image(data: object) -> UInt8[Tensor, "3 h w"]:
    """Decode one encoded image (uint8 1-D tensor of PNG or JPEG bytes) to uint8 [3, H, W]
    RGB; 16-bit PNGs are scaled to 8 bits (x 255 / 65535, rounded). Through the one image
    door, ``usplat_dr.io.user_files``.

    Raises ``BadSceneError`` when the bytes are not a readable PNG or JPEG (or claim more
    than ``MAX_IMAGE_PIXELS`` pixels)."""
    if not is_plain(data) or data.dtype != torch.uint8 or data.ndim != 1:
        raise BadSceneError("an image is not a uint8 1-D tensor of encoded bytes")
    try:
        with open_image(data.numpy().tobytes(), "an image") as im:
            arr = rgb8(im)
    except ValueError as e:
        raise BadSceneError(str(e)) from None
    return torch.from_numpy(arr.copy()).permute(2, 0, 1)


def is_plain(t: object) -> bool:
    """A tensor the readers can use: dense (strided) and on the CPU; a sparse, meta or
    quantised tensor in a record makes the scene malformed."""
    return (isinstance(t, Tensor) and t.layout == torch.strided and t.device.type == "cpu"
            and not t.is_quantized)


# ---- Chunks and index ----

REQUIRED_KEYS = {"key": str, "url": str, "timestamps": Tensor, "cameras": Tensor, "images": list}


def check_scene(scene: object) -> None:
    """Raise ``BadSceneError`` unless ``scene`` has the documented structure."""
    if not isinstance(scene, dict):
        raise BadSceneError(f"a scene record is a {type(scene).__name__}, not a dict")
    for key, typ in REQUIRED_KEYS.items():
        if key not in scene:
            raise BadSceneError(f"scene record lacks {key!r}")
        if not isinstance(scene[key], typ):
            raise BadSceneError(f"scene[{key!r}] is a {type(scene[key]).__name__}, "
                                f"expected {typ.__name__}")
    for key, value in scene.items():
        if isinstance(value, Tensor) and not is_plain(value):
            raise BadSceneError(f"scene[{key!r}] is a {value.layout} tensor on "
                                f"{value.device}, not a dense CPU tensor")
    v = len(scene["images"])
    if scene["cameras"].shape != (v, 18):
        raise BadSceneError(f"cameras have shape {tuple(scene['cameras'].shape)}, expected "
                            f"({v}, 18) for {v} images")
    if scene["timestamps"].shape != (v,):
        raise BadSceneError(f"timestamps have shape {tuple(scene['timestamps'].shape)}, "
                            f"expected ({v},)")
    if "depths" in scene:
        d = scene["depths"]
        if not isinstance(d, Tensor) or d.ndim != 3 or not d.is_floating_point():
            raise BadSceneError("depths must be a float tensor [V, H, W]")
        if d.shape[0] != v:
            raise BadSceneError(f"depths have {d.shape[0]} frames, expected {v}")


def read_chunk(path: str | os.PathLike) -> list:
    """Load one chunk (a list of scene records, each checked later by ``check_scene``). Raises
    ``BadChunkError`` when it is unreadable."""
    path = Path(path)
    try:
        check_torch_archive(path, "chunk")
    except ValueError as e:
        raise BadChunkError(str(e)) from None
    try:
        chunk = torch.load(path, weights_only=True, map_location="cpu")
    except Exception as e:  # truncated zip, pickle errors, I/O errors: all mean "unreadable"
        first = next((line.strip() for line in str(e).splitlines()
                      if line.strip() and "Weights only load failed" not in line), "")
        raise BadChunkError(f"{path}: cannot be loaded ({type(e).__name__}: "
                            f"{first[:200]})") from e
    if not isinstance(chunk, list):
        raise BadChunkError(f"{path}: holds a {type(chunk).__name__}, not a list of scenes")
    return chunk


def write_chunk(path: str | os.PathLike, scenes: Sequence[dict]) -> Path:
    """``torch.save`` a list of scene dicts, atomically, after checking their structure."""
    for scene in scenes:
        check_scene(scene)
    return torch_save(list(scenes), path)


def read_index(stage_dir: str | os.PathLike) -> dict[str, str]:
    """Read ``<stage_dir>/index.json`` (scene key -> chunk file name)."""
    path = Path(stage_dir) / "index.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist: every stage folder needs an index.json "
                                "mapping scene keys to chunk files (write one with "
                                "usplat_dr.data.chunks.write_index)")
    try:
        index = json.loads(path.read_text(encoding="utf-8"))
    except RecursionError:  # JSON nested deeper than Python's recursion limit
        raise ValueError(f"{path} is nested too deeply to be an index.json") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path} is not valid JSON ({e}); rebuild it with "
                         f"usplat_dr.data.chunks.write_index(stage_dir, index_chunks(stage_dir))"
                         ) from None
    if not isinstance(index, dict) or not all(isinstance(v, str) for v in index.values()):
        raise ValueError(f"{path} must hold a JSON object (scene key -> chunk file name)")
    # chunks live in the stage folder: a path ("../x.torch", "/abs", "") would read elsewhere
    bad = next((v for v in index.values() if v in ("", ".", "..") or Path(v).name != v), None)
    if bad is not None:
        raise ValueError(f"{path}: {bad!r} is not the name of a chunk file in {path.parent}")
    return index


def metadata_folder(out: str | os.PathLike, stage: str) -> Path:
    """Where a writer of ``stage`` (``usplat synth``, ``usplat import``) puts its evaluation
    indices and other metadata: ``out`` for the test stage (as always: evaluation reads
    ``<out>/evaluation_index_*.json``), ``out/<stage>`` for the others, so that the stages of
    one root never overwrite each other's.

    Examples:
        >>> metadata_folder("d", "test").as_posix(), metadata_folder("d", "train").as_posix()
        ('d', 'd/train')
    """
    return Path(out) if stage == "test" else Path(out) / stage


def stored_image_shape(root: str | os.PathLike, stage: str = "test") -> tuple[int, int] | None:
    """The (height, width) a dataset's ``stage`` images are stored at: the resolution
    ``usplat synth`` recorded in its ``synth.json``, else the size of the first image of the
    first scene of the stage's first chunk (a set of mixed sizes: that scene's); ``None`` when
    neither can be read (the loaders' own errors say why, later).

    Examples:
        >>> stored_image_shape("no/such/dataset") is None
        True
    """
    meta = metadata_folder(root, stage) / "synth.json"
    try:
        # a regular file of at most 1 MiB (a FIFO or a link to /dev/zero there is refused)
        shape = json.loads(read_bytes(meta, "synth.json", 2**20).decode("utf-8"))["resolution"]
        if (isinstance(shape, list) and len(shape) == 2
                and all(isinstance(n, int) and n > 0 for n in shape)):
            return int(shape[0]), int(shape[1])
    except (OSError, ValueError, KeyError, TypeError, RecursionError):
        pass
    try:
        scene = read_chunk(stage_chunks([root], stage)[0])[0]
        with open_image(scene["images"][0].numpy().tobytes(), "an image") as im:
            return im.size[1], im.size[0]
    except (OSError, ValueError, KeyError, IndexError, TypeError, AttributeError):
        return None


def write_index(stage_dir: str | os.PathLike, index: dict[str, str]) -> Path:
    return write_json(Path(stage_dir) / "index.json", dict(sorted(index.items())))


def index_chunks(stage_dir: str | os.PathLike) -> dict[str, str]:
    """Build the index of a stage folder by reading every chunk (for data without one)."""
    index = {}
    for chunk_path in sorted(Path(stage_dir).glob("*.torch")):
        for scene in read_chunk(chunk_path):
            index[scene["key"]] = chunk_path.name
    return index


class ChunkWriter:
    """Write scenes into ``<root>/<stage>/NNNNNN.torch`` chunks of about ``chunk_bytes`` each
    (and at most ``chunk_scenes`` scenes each, when given), plus ``index.json`` (written
    atomically after every chunk, so a killed writer leaves a consistent dataset).

    Examples:
        >>> import tempfile
        >>> with ChunkWriter(tempfile.mkdtemp(), "test") as w:
        ...     w.add({"key": "a", "url": "", "timestamps": torch.zeros(0, dtype=torch.int64),
        ...            "cameras": torch.zeros(0, 18), "images": []})
        >>> w.index
        {'a': '000000.torch'}
    """

    def __init__(self, root: str | os.PathLike, stage: str, chunk_bytes: int = 100_000_000,
                 chunk_scenes: int | None = None):
        if chunk_scenes is not None and chunk_scenes < 1:
            raise ValueError(f"chunk_scenes must be >= 1 (or None: no limit), got {chunk_scenes}")
        self.stage_dir = Path(root) / stage
        self.stage_dir.mkdir(parents=True, exist_ok=True)
        self.chunk_bytes = chunk_bytes
        self.chunk_scenes = chunk_scenes
        self.index: dict[str, str] = {}
        self._pending: list[dict] = []
        self._pending_bytes = 0
        self._next = 0

    def add(self, scene: dict) -> None:
        check_scene(scene)
        if scene["key"] in self.index or any(s["key"] == scene["key"] for s in self._pending):
            raise ValueError(f"scene key {scene['key']!r} written twice")
        self._pending.append(scene)
        self._pending_bytes += _nbytes(scene)
        if self._pending_bytes >= self.chunk_bytes or len(self._pending) == self.chunk_scenes:
            self.flush()

    def flush(self) -> None:
        if not self._pending:
            return
        name = f"{self._next:06d}.torch"
        write_chunk(self.stage_dir / name, self._pending)
        self.index.update({s["key"]: name for s in self._pending})
        write_index(self.stage_dir, self.index)
        self._pending, self._pending_bytes = [], 0
        self._next += 1

    def close(self) -> None:
        self.flush()
        if not self.index:
            write_index(self.stage_dir, {})

    def __enter__(self) -> "ChunkWriter":  # noqa: PYI034 (typing.Self needs Python 3.11)
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()


def _nbytes(obj: object) -> int:
    if isinstance(obj, Tensor):
        return obj.numel() * obj.element_size()
    if isinstance(obj, dict):
        return sum(_nbytes(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(_nbytes(v) for v in obj)
    return 64


def _chunk_file_ok(path: Path, root: Path) -> bool:
    """False, with a warning, for a chunk name that is not a regular file (a FIFO would block
    every reader) or that links outside ``root`` (refused like a ``../`` name)."""
    try:
        mode = path.stat().st_mode
    except OSError as e:
        log.warning("skipping chunk %s: cannot be read (%s)", path, e.strerror)
        return False
    if not stat.S_ISREG(mode):
        log.warning("skipping chunk %s: not a regular file (a FIFO, device or folder)", path)
        return False
    if not path.resolve().is_relative_to(root.resolve()):
        log.warning("skipping chunk %s: it links to %s, outside the dataset root %s (copy the "
                    "chunk into the root, or link the whole root)", path, path.resolve(), root)
        return False
    return True


def stage_chunks(roots: Iterable[str | os.PathLike], stage: str) -> list[Path]:
    """All chunk files of ``stage`` under the given roots, in order. Clear errors for a missing
    root or an empty stage."""
    chunks = []
    for root in roots:
        root = Path(root)
        if not root.is_dir():
            raise FileNotFoundError(f"dataset root {root} does not exist (check the 'roots' "
                                    "setting; it should hold train/ and test/ folders)")
        stage_dir = root / stage
        found = [p for p in sorted(stage_dir.glob("*.torch")) if _chunk_file_ok(p, root)]
        if not found:
            raise FileNotFoundError(f"{stage_dir} holds no .torch chunks: the stage '{stage}' is "
                                    f"empty or missing under {root}")
        chunks.extend(found)
    return chunks
