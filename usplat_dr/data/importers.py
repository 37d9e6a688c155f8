"""Import the formats users have (a COLMAP sparse model, a nerfstudio ``transforms.json``) into
the chunk format (``usplat import``).

Both readers return one ``ImportedScene``: image paths, OpenCV camera-to-world extrinsics,
normalised intrinsics (fx/W, fy/H, cx/W, cy/H, as in the chunk format) and, from COLMAP, the
sparse 3D points. ``import_scene`` writes it as a dataset root: ``<out>/<stage>/000000.torch``
+ ``index.json`` and ``<out>/evaluation_index_standard.json`` (the layout ``usplat synth``
writes), with a ``near_far`` record per scene.

Conventions, each tested in tests/data/test_importers.py:

- COLMAP (https://colmap.github.io/format.html) stores world-to-camera poses: ``images``
  give ``qvec`` (w, x, y, z; real part first) and ``tvec``, so ``x_cam = R(q) x_world + t``,
  in OpenCV axes (+X right, +Y down, +Z forward). Intrinsics are in pixels, with the image
  origin at the top-left corner of the top-left pixel (its centre is (0.5, 0.5)): the same
  continuous coordinates as normalised intrinsics, so cx/W needs no half-pixel shift.
- nerfstudio (https://docs.nerf.studio/quickstart/data_conventions.html) stores
  camera-to-world ``transform_matrix`` in OpenGL axes (+X right, +Y up, +Z backward): the
  camera's y and z axes are flipped, ``c2w_opencv = c2w_opengl @ diag(1, -1, -1, 1)``.
  ``applied_transform`` (the world change nerfstudio applied to COLMAP poses) is already in
  the matrices; it is ignored, as is any scene scale: the poses are used as written.
- Lens distortion is not undistorted here: a distorted model with non-zero coefficients is an
  error unless ``ignore_distortion`` (the coefficients are dropped with a warning; fine for
  the small distortion of phone cameras, wrong for wide lenses, which need
  ``colmap image_undistorter`` first).
- Frames are ordered by image name (the evaluation index counts frames in that order).
"""

import json
import logging
import math
import os
import re
import shutil
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from usplat_dr.data.chunks import ChunkWriter, encode_image, matrices_to_cameras, metadata_folder
from usplat_dr.io import write_json
from usplat_dr.io.atomic import remove_temporaries_of
from usplat_dr.io.user_files import check_resize, inside, read_bytes, read_image, regular_file

log = logging.getLogger(__name__)


@dataclass
class ImportedScene:
    """One scene as read from a COLMAP model or a transforms.json, in the chunk format's
    conventions."""

    image_paths: list[Path]  # V image files, ordered by name
    extrinsics: np.ndarray  # [V, 4, 4] float64 camera-to-world, OpenCV axes
    intrinsics: np.ndarray  # [V, 3, 3] float64 normalised: fx/W, fy/H, cx/W, cy/H
    image_shapes: np.ndarray  # [V, 2] int (H, W) the cameras were calibrated at
    points: np.ndarray | None  # [N, 3] float64 world points (COLMAP), or None
    source: Path  # the folder read


# ---- COLMAP ----

#: COLMAP camera models: id -> (name, number of parameters), from colmap/src/colmap/sensor/
#: models.h (and scripts/python/read_write_model.py).
COLMAP_MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
}
COLMAP_MODEL_IDS = {name: (i, n) for i, (name, n) in COLMAP_MODELS.items()}
#: Models whose distortion may be dropped (``ignore_distortion``): pinhole + radial/tangential
#: terms. Fisheye and FOV models map rays differently: undistort them first.
DROPPABLE = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")
UNDISTORT = ("undistort the images first (colmap image_undistorter --output_type COLMAP "
             "writes a PINHOLE model)")


@dataclass
class ColmapCamera:
    model: str
    width: int
    height: int
    params: np.ndarray  # float64, COLMAP's order for the model


def colmap_pinhole(cam: ColmapCamera, where: str, ignore_distortion: bool = False
                   ) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) in pixels of a COLMAP camera; a ``ValueError`` naming ``where`` for a
    model that is not a pinhole (unless its distortion is zero, or droppable and
    ``ignore_distortion``)."""
    p = cam.params
    if cam.model == "SIMPLE_PINHOLE":
        return p[0], p[0], p[1], p[2]
    if cam.model == "PINHOLE":
        return p[0], p[1], p[2], p[3]
    if cam.model not in DROPPABLE:
        raise ValueError(f"{where}: camera model {cam.model} is not supported (PINHOLE, "
                         f"SIMPLE_PINHOLE; {', '.join(DROPPABLE)} with --ignore-distortion): "
                         f"{UNDISTORT}")
    if cam.model == "OPENCV":
        pinhole, distortion = (p[0], p[1], p[2], p[3]), p[4:]
    else:  # SIMPLE_RADIAL f, cx, cy, k; RADIAL f, cx, cy, k1, k2
        pinhole, distortion = (p[0], p[0], p[1], p[2]), p[3:]
    if np.any(distortion != 0):
        if not ignore_distortion:
            raise ValueError(f"{where}: camera model {cam.model} has distortion "
                             f"{distortion.tolist()}: {UNDISTORT}, or pass "
                             "--ignore-distortion to drop it")
        log.warning("%s: dropping the %s distortion %s (--ignore-distortion): straight lines "
                    "near the image borders will not project exactly", where, cam.model,
                    distortion.tolist())
    return pinhole


#: Cameras, images or frames one camera file may describe: more is a damaged or hostile file
#: (a capture of 100,000 photos is far past what two-view models read), refused before any
#: per-record work.
MAX_CAMERAS = 100_000
#: The longest line a COLMAP text file may hold (an images.txt POINTS2D line of 1,000,000
#: keypoints is about 40 MB).
MAX_LINE_BYTES = 64 * 2**20
#: Image sizes and focal lengths a camera may have, in pixels.
MAX_IMAGE_SIDE = 65_536
MAX_FOCAL = 1e6


def check_camera(width, height, fx: float, fy: float, cx: float, cy: float, where: str
                 ) -> None:
    """A camera read from a file: a whole-pixel size in 1..``MAX_IMAGE_SIDE``, focal lengths
    in (0, ``MAX_FOCAL``] and a finite principal point; else a ``ValueError`` naming
    ``where`` (the camera file and camera).

    Examples:
        >>> check_camera(1e300, 1e300, 500.0, 500.0, 320.0, 240.0, "t.json")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: t.json: the image size must be whole pixels in 1..65,536, got 1e+300 x ...
    """
    sizes_ok = all(isinstance(s, (int, float, np.integer, np.floating)) and math.isfinite(s)
                   and float(s).is_integer() and 1 <= s <= MAX_IMAGE_SIDE
                   for s in (width, height))
    if not sizes_ok:
        raise ValueError(f"{where}: the image size must be whole pixels in 1..{MAX_IMAGE_SIDE:,}, "
                         f"got {width} x {height}")
    if not all(math.isfinite(f) and 0 < f <= MAX_FOCAL for f in (fx, fy)):
        raise ValueError(f"{where}: the focal lengths must be in (0, {MAX_FOCAL:.0e}] pixels, "
                         f"got fx {fx}, fy {fy}")
    if not (math.isfinite(cx) and math.isfinite(cy)):
        raise ValueError(f"{where}: the principal point must be finite, got {cx}, {cy}")


def check_count(count: int, path: Path, what: str) -> int:
    """``count`` records declared by ``path``, refused past ``MAX_CAMERAS``."""
    if count > MAX_CAMERAS:
        raise ValueError(f"{path} declares {count:,} {what}, more than the {MAX_CAMERAS:,} a "
                         f"camera file may hold: a damaged file, or keep every k-th")
    return count


def _text_lines(path: Path):
    """The lines of a COLMAP text file (comments and blank lines kept: images.txt pairs
    lines, and an image with no 2D points has an empty second line), streamed: each at most
    ``MAX_LINE_BYTES``, so a large file of one endless line stops at the first."""
    regular_file(path, "COLMAP file")
    with open(path, "rb") as f:
        n = 0
        while line := f.readline(MAX_LINE_BYTES + 1):
            n += 1
            if len(line) > MAX_LINE_BYTES:
                raise ValueError(f"{path}:{n}: a line longer than {MAX_LINE_BYTES:,} bytes: not "
                                 f"a COLMAP text file")
            try:
                yield line.decode("utf-8").rstrip("\r\n")
            except UnicodeDecodeError as e:
                raise ValueError(f"{path}:{n} is not UTF-8 text ({e}): not a COLMAP text "
                                 f"file") from None


def read_colmap_cameras_text(path: Path) -> dict[int, ColmapCamera]:
    """cameras.txt: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`` per line."""
    cameras = {}
    for n, line in enumerate(_text_lines(path), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        e = line.split()
        model = e[1]
        if model not in COLMAP_MODEL_IDS:
            raise ValueError(f"{path}:{n}: unknown camera model {model!r} (known: "
                             f"{', '.join(COLMAP_MODEL_IDS)}): {UNDISTORT}")
        expected = COLMAP_MODEL_IDS[model][1]
        if len(e) != 4 + expected:
            raise ValueError(f"{path}:{n}: camera model {model} needs {expected} parameters, "
                             f"got {len(e) - 4}")
        camera = ColmapCamera(model, int(e[2]), int(e[3]), np.array([float(x) for x in e[4:]]))
        _check_colmap_camera(camera, f"{path}:{n}")
        cameras[int(e[0])] = camera
        check_count(len(cameras), path, "cameras")
    return cameras


def _check_colmap_camera(cam: ColmapCamera, where: str) -> None:
    """``check_camera`` on a COLMAP camera's size and pinhole part (where it is read)."""
    p = cam.params
    n = COLMAP_MODEL_IDS[cam.model][1]
    if len(p) != n or not np.all(np.isfinite(p)):
        raise ValueError(f"{where}: camera model {cam.model} needs {n} finite parameters, got "
                         f"{p.tolist()}")
    two_focals = cam.model in ("PINHOLE", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE",
                               "FOV", "THIN_PRISM_FISHEYE")
    fx, fy, cx, cy = (p[0], p[1], p[2], p[3]) if two_focals else (p[0], p[0], p[1], p[2])
    check_camera(cam.width, cam.height, float(fx), float(fy), float(cx), float(cy), where)


def read_colmap_images_text(path: Path) -> dict[int, tuple[np.ndarray, np.ndarray, int, str]]:
    """images.txt: two lines per image, ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` then
    its 2D points (unused). Returns id -> (qvec (w, x, y, z), tvec, camera id, name)."""
    images = {}
    lines = iter(enumerate(_text_lines(path), 1))
    for n, line in lines:
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        e = line.split()
        if len(e) < 10:
            raise ValueError(f"{path}:{n}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID "
                             f"NAME, got {line.strip()[:80]!r}")
        images[int(e[0])] = (np.array([float(x) for x in e[1:5]]),
                             np.array([float(x) for x in e[5:8]]), int(e[8]),
                             " ".join(e[9:]))
        check_count(len(images), path, "images")
        next(lines, None)  # the POINTS2D line (possibly empty)
    return images


def read_colmap_points_text(path: Path) -> np.ndarray:
    """points3D.txt: ``POINT3D_ID X Y Z R G B ERROR TRACK[]``; returns xyz [N, 3]."""
    xyz = [[float(x) for x in line.split()[1:4]] for line in _text_lines(path)
           if line.strip() and not line.lstrip().startswith("#")]
    return np.array(xyz, dtype=np.float64).reshape(-1, 3)


class _Reader:
    """Little-endian struct reads from a COLMAP .bin file, streamed from the file (never more
    than a record at a time in memory), with an error naming the file when it ends early or
    holds bytes after its last record. A context manager."""

    #: The longest image name read (COLMAP's are file names).
    MAX_NAME = 4096

    def __init__(self, path: Path):
        self.path = regular_file(path, "COLMAP file")
        self.file = open(self.path, "rb")  # noqa: SIM115 (closed by __exit__)
        self.size, self.pos = os.fstat(self.file.fileno()).st_size, 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.file.close()
        return False

    def _early(self, what: str) -> ValueError:
        return ValueError(f"{self.path}: ends early at byte {self.pos} ({what}; a truncated or "
                          "damaged file: export the model again with colmap model_converter)")

    def read(self, fmt: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        data = self.file.read(size) if self.pos + size <= self.size else b""
        if len(data) != size:
            raise self._early("a truncated file")
        self.pos += size
        return struct.unpack("<" + fmt, data)

    def count(self, what: str) -> int:
        """A uint64 record count, refused past ``MAX_CAMERAS``."""
        return check_count(self.read("Q")[0], self.path, what)

    def skip(self, nbytes: int) -> None:
        if self.pos + nbytes > self.size:  # (a count read from the file may claim 2^64)
            raise self._early(f"a record claims {nbytes:,} more bytes")
        self.pos += nbytes
        self.file.seek(self.pos)

    def name(self) -> str:
        raw = bytearray()
        while (byte := self.file.read(1)) != b"\0":
            if not byte:
                raise ValueError(f"{self.path}: an image name has no terminating NUL "
                                 f"(truncated)")
            raw += byte
            if len(raw) > self.MAX_NAME:
                raise ValueError(f"{self.path}: an image name at byte {self.pos} is longer "
                                 f"than {self.MAX_NAME} bytes (a damaged file)")
        try:
            out = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise ValueError(f"{self.path}: an image name at byte {self.pos} is not UTF-8 (a "
                             "damaged file)") from None
        self.pos += len(raw) + 1
        return out

    def end(self) -> None:
        """The file holds nothing after its last record (a sparse or padded file would
        otherwise pass as a short model)."""
        if self.pos != self.size:
            raise ValueError(f"{self.path} holds {self.size - self.pos:,} bytes after its last "
                             f"record (byte {self.pos}): a damaged file; export the model "
                             f"again with colmap model_converter")


def read_colmap_cameras_binary(path: Path) -> dict[int, ColmapCamera]:
    """cameras.bin: uint64 count; per camera int32 id, int32 model id, uint64 width, uint64
    height, then the model's float64 parameters."""
    cameras = {}
    with _Reader(path) as r:
        for _ in range(r.count("cameras")):
            cam_id, model_id, width, height = r.read("iiQQ")
            if model_id not in COLMAP_MODELS:
                raise ValueError(f"{path}: camera {cam_id} has unknown model id {model_id} "
                                 f"(known: 0-10): {UNDISTORT}")
            model, n = COLMAP_MODELS[model_id]
            camera = ColmapCamera(model, width, height, np.array(r.read(f"{n}d")))
            _check_colmap_camera(camera, f"{path} camera {cam_id}")
            cameras[cam_id] = camera
        r.end()
    return cameras


def read_colmap_images_binary(path: Path) -> dict[int, tuple[np.ndarray, np.ndarray, int, str]]:
    """images.bin: uint64 count; per image int32 id, float64 qvec (w, x, y, z), float64 tvec,
    int32 camera id, NUL-terminated name, uint64 point count, then (float64 x, float64 y,
    int64 point id) per 2D point (skipped)."""
    images = {}
    with _Reader(path) as r:
        for _ in range(r.count("images")):
            image_id, *qt, cam_id = r.read("idddddddi")
            name = r.name()
            r.skip(r.read("Q")[0] * struct.calcsize("<ddq"))
            images[image_id] = (np.array(qt[:4]), np.array(qt[4:]), cam_id, name)
        r.end()
    return images


#: 3D points a points3D file may hold (a large COLMAP reconstruction has a few million).
MAX_POINTS = 50_000_000


def read_colmap_points_binary(path: Path) -> np.ndarray:
    """points3D.bin: uint64 count; per point uint64 id, float64 xyz, uint8 rgb, float64 error,
    uint64 track length, then (int32 image id, int32 point2D index) per track element."""
    xyz = []
    with _Reader(path) as r:
        count = r.read("Q")[0]
        record = struct.calcsize("<QdddBBBdQ")
        if count > MAX_POINTS or count * record > r.size - r.pos:
            raise ValueError(f"{path} declares {count:,} points, more than its "
                             f"{r.size:,} bytes (or {MAX_POINTS:,}) can hold: a damaged file")
        for _ in range(count):
            xyz.append(r.read("QdddBBBd")[1:4])
            r.skip(r.read("Q")[0] * struct.calcsize("<ii"))
        r.end()
    return np.array(xyz, dtype=np.float64).reshape(-1, 3)


def qvec_to_rotation(qvec: np.ndarray) -> np.ndarray:
    """[3, 3] rotation of a quaternion stored real part first (w, x, y, z), as COLMAP does
    (normalised first: text files round it).

    Examples:
        >>> qvec_to_rotation(np.array([0.0, 0.0, 0.0, 1.0])).round(6).tolist()  # 180 deg about z
        [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]
    """
    norm = float(np.linalg.norm(qvec))
    if not math.isfinite(norm) or norm < 1e-8:
        raise ValueError(f"quaternion {np.asarray(qvec).tolist()} is zero or not finite: not "
                         f"a rotation")
    w, x, y, z = qvec / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def find_colmap_model(folder: Path) -> Path:
    """The folder holding cameras.{bin,txt}: ``folder`` itself, ``folder/sparse/0`` or
    ``folder/sparse`` (COLMAP's project layout)."""
    for candidate in (folder, folder / "sparse" / "0", folder / "sparse"):
        if (candidate / "cameras.bin").is_file() or (candidate / "cameras.txt").is_file():
            return candidate
    raise FileNotFoundError(f"{folder / 'cameras.bin'} (or cameras.txt) does not exist, nor "
                            f"under sparse/0: point --colmap at the sparse model folder, "
                            f"e.g. project/sparse/0")


def read_colmap(folder: str | os.PathLike, images: str | os.PathLike | None = None,
                ignore_distortion: bool = False) -> ImportedScene:
    """Read a COLMAP sparse model (binary preferred when both exist, as COLMAP's own
    read_write_model does) and find its images: in ``images`` when given, else the first of
    ``<model>/images``, ``<model>/../images``, ``<model>/../../images`` that exists."""
    model = find_colmap_model(Path(folder))
    ext = ".bin" if (model / "cameras.bin").is_file() else ".txt"
    readers = {".bin": (read_colmap_cameras_binary, read_colmap_images_binary,
                        read_colmap_points_binary),
               ".txt": (read_colmap_cameras_text, read_colmap_images_text,
                        read_colmap_points_text)}[ext]
    images_file = model / f"images{ext}"
    if not images_file.is_file():
        raise FileNotFoundError(f"{images_file} does not exist: a COLMAP model needs "
                                f"cameras{ext}, images{ext} (and points3D{ext}) together")
    cameras = readers[0](model / f"cameras{ext}")
    records = readers[1](images_file)
    if not records:
        raise ValueError(f"{images_file} holds no registered images: run the mapper again")
    points_file = model / f"points3D{ext}"
    points = readers[2](points_file) if points_file.is_file() else None
    if points is None:
        log.warning("%s does not exist: near/far need --near and --far", points_file)

    image_dir = _colmap_image_dir(model, images)
    ordered = sorted(records.values(), key=lambda rec: rec[3])
    c2w, intr, shapes, paths = [], [], [], []
    for qvec, tvec, cam_id, name in ordered:
        if cam_id not in cameras:
            raise ValueError(f"{images_file}: image {name!r} names camera {cam_id}, which "
                             f"{model / ('cameras' + ext)} does not have")
        cam = cameras[cam_id]
        fx, fy, cx, cy = colmap_pinhole(cam, f"{model / ('cameras' + ext)} camera {cam_id}",
                                        ignore_distortion)
        try:
            w2c = np.eye(4)
            w2c[:3, :3] = qvec_to_rotation(qvec)
            w2c[:3, 3] = tvec
            c2w.append(np.linalg.inv(rigid(w2c, "the pose")))
            intr.append(normalised_intrinsics(fx, fy, cx, cy, cam.width, cam.height))
        except ValueError as e:
            raise ValueError(f"{images_file}: image {name!r}: {e}") from None
        shapes.append((cam.height, cam.width))
        paths.append(inside(image_dir, name, f"{images_file}: image name"))
    refuse_duplicates(paths, images_file, "images")
    return ImportedScene(paths, np.stack(c2w), np.stack(intr), np.array(shapes), points, model)


def _colmap_image_dir(model: Path, images: str | os.PathLike | None) -> Path:
    if images is not None:
        if not Path(images).is_dir():
            raise FileNotFoundError(f"--images {images} is not a folder")
        return Path(images)
    for candidate in (model / "images", model.parent / "images", model.parent.parent / "images"):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(f"no images folder next to {model} (looked in images/, ../images/ "
                            f"and ../../images/): pass --images DIR")


def rigid(m: np.ndarray, what: str) -> np.ndarray:
    """``m`` [4, 4] when it is a rigid camera-to-world transform (finite, last row 0 0 0 1, a
    rotation: orthonormal to 1e-3, determinant +1), else a ``ValueError`` naming ``what``.

    Examples:
        >>> rigid(np.diag([2.0, 2.0, 2.0, 1.0]), "pose")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: pose is not a rigid transform: its 3x3 part is not a rotation (R^T R ...
    """
    if not np.isfinite(m).all():
        raise ValueError(f"{what} is not finite (NaN or infinite entries)")
    if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
        raise ValueError(f"{what} is not a rigid transform: its last row is {m[3].tolist()}, "
                         f"not [0, 0, 0, 1]")
    r = m[:3, :3]
    off = float(np.abs(r.T @ r - np.eye(3)).max())
    det = float(np.linalg.det(r))
    if off > 1e-3 or det < 0:
        raise ValueError(f"{what} is not a rigid transform: its 3x3 part is not a rotation "
                         f"(R^T R differs from I by {off:.3g}, det {det:.3g}): undo the scale "
                         f"first")
    return m


def normalised_intrinsics(fx: float, fy: float, cx: float, cy: float, width: int,
                          height: int) -> np.ndarray:
    """[3, 3] intrinsics normalised by the image size: row 0 / W, row 1 / H (the chunk
    format's). A resize, uniform or not, leaves them unchanged: fx and cx scale with W.

    Examples:
        >>> normalised_intrinsics(500.0, 400.0, 320.0, 240.0, 640, 480).tolist()
        [[0.78125, 0.0, 0.5], [0.0, 0.8333333333333334, 0.5], [0.0, 0.0, 1.0]]
    """
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)):
        raise ValueError(f"a camera's focal length and centre must be finite, got fx {fx}, "
                         f"fy {fy}, cx {cx}, cy {cy}")
    if width <= 0 or height <= 0 or fx <= 0 or fy <= 0:
        raise ValueError(f"a camera needs a positive size and focal length, got {width}x"
                         f"{height}, fx {fx}, fy {fy}")
    return np.array([[fx / width, 0.0, cx / width], [0.0, fy / height, cy / height],
                     [0.0, 0.0, 1.0]])


# ---- nerfstudio ----

#: OpenGL camera axes (+Y up, +Z backward) to OpenCV's (+Y down, +Z forward): flip y and z.
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
NERFSTUDIO_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
NERFSTUDIO_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
#: Bytes a transforms.json may hold (10,000 frames with per-frame intrinsics are about 10 MB).
MAX_JSON_BYTES = 256 * 2**20


def read_nerfstudio(folder: str | os.PathLike, ignore_distortion: bool = False,
                    name: str = "transforms.json", distinct_images: bool = True
                    ) -> ImportedScene:
    """Read ``<folder>/<name>`` (nerfstudio's format; ``transforms.json`` by default, any
    file in that layout, a camera path say, otherwise): intrinsics ``fl_x``, ``fl_y``,
    ``cx``, ``cy``, ``w``, ``h`` at the top level or per frame (a frame's own win), and per
    frame ``file_path`` (relative to ``folder``) and ``transform_matrix`` (camera-to-world,
    OpenGL axes). ``distinct_images``: one image per frame (a camera path's frames, whose
    images are never read, may share one)."""
    folder = Path(folder)
    path = folder / name
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist: point --nerfstudio at the folder "
                                "holding transforms.json (ns-process-data's output)")
    try:
        meta = json.loads(read_bytes(path, "camera file", MAX_JSON_BYTES).decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path} is not valid JSON ({e})") from None
    except RecursionError:
        raise ValueError(f"{path} nests its JSON too deeply: not a transforms.json") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) \
            or not meta["frames"]:
        raise ValueError(f"{path} has no 'frames' list: not a nerfstudio transforms.json")
    if "applied_transform" in meta or "scale" in meta:
        log.info("%s: 'applied_transform'/'scale' are ignored: the poses are used as written "
                 "(the world frame does not matter to the model)", path)
    if "ply_file_path" in meta:
        log.info("%s: the point cloud %s is not read: near/far need --near and --far", path,
                 meta["ply_file_path"])
    check_count(len(meta["frames"]), path, "frames")
    if not all(isinstance(f, dict) for f in meta["frames"]):
        raise ValueError(f"{path}: every frame must be an object with 'file_path' and "
                         f"'transform_matrix'")
    frames = sorted(meta["frames"], key=lambda f: str(f.get("file_path", "")))
    c2w, intr, shapes, paths = [], [], [], []
    for i, frame in enumerate(frames):
        where = f"{path} frame {frame.get('file_path', i)!r}"
        if "file_path" not in frame or "transform_matrix" not in frame:
            raise ValueError(f"{where}: needs 'file_path' and 'transform_matrix'")
        get = {**meta, **frame}.get
        missing = [k for k in ("fl_x", "w", "h") if get(k) is None]
        if missing:
            raise ValueError(f"{where}: no {', '.join(missing)} (top level or per frame): "
                             "add the intrinsics in pixels")
        model = get("camera_model", "OPENCV")
        if model not in NERFSTUDIO_MODELS:
            raise ValueError(f"{where}: camera_model {model!r} is not supported "
                             f"({', '.join(NERFSTUDIO_MODELS)}): {UNDISTORT}")
        distortion = {k: float(get(k)) for k in NERFSTUDIO_DISTORTION if get(k)}
        if distortion:
            if not ignore_distortion:
                raise ValueError(f"{where}: distortion {distortion}: {UNDISTORT}, or pass "
                                 "--ignore-distortion to drop it")
            log.warning("%s: dropping the distortion %s (--ignore-distortion)", where,
                        distortion)
        try:
            w, h = int(get("w")), int(get("h"))
            fx = float(get("fl_x"))
            fy = float(get("fl_y", fx))
            m = np.asarray(frame["transform_matrix"], dtype=np.float64)
            if m.shape == (3, 4):
                m = np.concatenate([m, [[0.0, 0.0, 0.0, 1.0]]])
            if m.shape != (4, 4):
                raise ValueError(f"transform_matrix must be 4x4 (or 3x4), got {m.shape}")
            cx, cy = float(get("cx", w / 2)), float(get("cy", h / 2))
            check_camera(w, h, fx, fy, cx, cy, "the camera")
            c2w.append(rigid(m, "transform_matrix") @ OPENGL_TO_OPENCV)
            intr.append(normalised_intrinsics(fx, fy, cx, cy, w, h))
        except (TypeError, ValueError, OverflowError) as e:
            raise ValueError(f"{where}: {e}") from None
        shapes.append((h, w))
        paths.append(inside(folder, frame["file_path"], f"{where}: file_path"))
    if distinct_images:
        refuse_duplicates(paths, path, "frames")
    return ImportedScene(paths, np.stack(c2w), np.stack(intr), np.array(shapes), None, folder)


def refuse_duplicates(paths: list[Path], source: Path, what: str) -> None:
    """One image per camera: an image named by two of ``source``'s ``what`` (at two poses, or
    twice at one) is refused, naming it."""
    seen = {}
    for path in paths:
        key = os.path.normpath(path)
        if key in seen:
            raise ValueError(f"{source}: {what} name the image {path} twice: one image per "
                             f"camera (remove the duplicate)")
        seen[key] = path


# ---- Writing a dataset root ----

#: near/far from sparse points: percentiles of their depths over all views, widened by these
#: factors (a point cloud never reaches the nearest and farthest surfaces seen).
DEPTH_PERCENTILES = (1.0, 99.0)
NEAR_FAR_MARGIN = (0.8, 1.2)


def visible_depths(points: np.ndarray, extrinsics: np.ndarray, intrinsics: np.ndarray
                   ) -> np.ndarray:
    """The camera-space depths of the points each camera sees (in front, inside the image),
    over all cameras, concatenated."""
    depths = []
    for c2w, k in zip(extrinsics, intrinsics):
        cam = (points - c2w[:3, 3]) @ c2w[:3, :3]  # [N, 3] = R^T (p - c), camera space
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = k[0, 0] * cam[:, 0] / z + k[0, 2]
            v = k[1, 1] * cam[:, 1] / z + k[1, 2]
        depths.append(z[(z > 0) & (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)])
    return np.concatenate(depths)


def near_far_from_points(points: np.ndarray, extrinsics: np.ndarray,
                         intrinsics: np.ndarray) -> tuple[float, float]:
    """(near, far): the 1st and 99th percentile of the camera-space depths of the points each
    view sees (in front, inside the image), over all views, times 0.8 and 1.2.

    Examples:
        >>> pts = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 4.0]])
        >>> near_far_from_points(pts, np.eye(4)[None], np.array([[[1, 0, .5], [0, 1, .5],
        ...                                                        [0, 0, 1.]]]))
        (1.616, 4.776)
    """
    depths = visible_depths(points, extrinsics, intrinsics)
    if depths.size == 0:
        raise ValueError("no sparse point lies in front of a camera: give --near and --far")
    lo, hi = np.percentile(depths, DEPTH_PERCENTILES)
    return round(float(lo * NEAR_FAR_MARGIN[0]), 6), round(float(hi * NEAR_FAR_MARGIN[1]), 6)


def standard_entry(views: int, context: tuple[int, int] | None = None, targets: int = 3
                   ) -> dict:
    """The evaluation-index entry ``usplat synth``'s ``standard`` split has: two context
    frames ``gap = max(2, round(V / 3))`` apart (centred here, where synth draws the left one
    at random), up to ``targets`` frames evenly spaced between them (both context frames when
    none lies between).

    Examples:
        >>> standard_entry(10)
        {'context': [3, 6], 'target': [4, 5]}
        >>> standard_entry(30, context=(0, 20))
        {'context': [0, 20], 'target': [5, 10, 15]}
    """
    if context is None:
        if views < 2:
            raise ValueError(f"a scene needs at least 2 images for an evaluation index, got "
                             f"{views}")
        gap = min(views - 1, max(2, round(views / 3)))
        left = (views - 1 - gap) // 2
        context = (left, left + gap)
    left, right = context
    if not 0 <= left < right < views:
        raise ValueError(f"--context must be two frames 0 <= I < J < {views}, got "
                         f"{left} {right}")
    inner = list(range(left + 1, right))
    if len(inner) > targets:
        inner = sorted({inner[round(x)] for x in np.linspace(0, len(inner) - 1,
                                                             targets + 2)[1:-1]})
    return {"context": [left, right], "target": inner or [left, right]}


def load_image(path: Path, calibrated: tuple[int, int], resolution: tuple[int, int] | None
               ) -> np.ndarray:
    """[H, W, 3] uint8 of one image, resized (Lanczos) to ``resolution`` (H, W) when given. The
    file's aspect ratio must be the calibrated one (the model was solved at another size,
    e.g. COLMAP on full-size images and images_2/ holding halves: fine)."""
    if not path.is_file():
        raise FileNotFoundError(f"image {path} does not exist (named by the model): pass "
                                "--images DIR (COLMAP) or fix file_path (nerfstudio)")
    image = read_image(path)
    h, w = image.shape[:2]
    ch, cw = calibrated
    # 1% covers sizes rounded when images were downscaled by 2, 4 or 8
    if abs(w / h - cw / ch) > 0.01 * cw / ch:
        raise ValueError(f"image {path} is {w}x{h}, but its camera was calibrated at "
                         f"{cw}x{ch} (another aspect ratio): use the images the model "
                         "was solved on")
    if resolution is not None and (h, w) != tuple(resolution):
        check_resize((h, w), tuple(resolution), f"image {path}")
        im = Image.fromarray(image).resize((resolution[1], resolution[0]),
                                           Image.Resampling.LANCZOS)
        return np.asarray(im)
    return image


def scene_key(source: Path) -> str:
    """A scene key from a folder name (``project/sparse/0`` -> ``project``)."""
    parts = [p for p in source.resolve().parts if p not in ("0", "sparse", "/")]
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", parts[-1] if parts else "scene")


def import_scene(scene: ImportedScene, out: str | os.PathLike, stage: str = "test",
                 resolution: tuple[int, int] | None = None, key: str | None = None,
                 context: tuple[int, int] | None = None, near: float | None = None,
                 far: float | None = None, fmt: str = "png") -> dict:
    """Write ``scene`` as a dataset root ``out``: ``<out>/<stage>/000000.torch`` +
    ``index.json`` (one record: ``key``, ``url`` (the source folder), ``timestamps`` (frame
    numbers), ``cameras``, ``images``, ``near_far``, ``names`` (the image file names)) and
    its ``evaluation_index_standard.json`` (``standard_entry``) in
    ``chunks.metadata_folder(out, stage)`` (``out`` for the test stage, ``out/train`` for the
    train stage). ``near``/``far`` default
    to ``near_far_from_points`` (an error without points). Returns a summary dict."""
    if stage not in ("train", "test"):
        raise ValueError(f"stage must be 'train' or 'test', got {stage!r}")
    if fmt not in ("png", "jpeg"):
        raise ValueError(f"fmt must be 'png' or 'jpeg', got {fmt!r}")
    if resolution is not None and (len(resolution) != 2 or min(resolution) < 1):
        raise ValueError(f"resolution must be (H, W) >= 1, got {resolution}")
    out = Path(out)
    if any((out / stage).glob("*.torch")) or (out / stage / "index.json").exists():
        raise ValueError(f"{out / stage} already holds a dataset (index.json, chunks): pass a "
                         "new --out")
    if (out / stage).is_dir() and any((out / stage).iterdir()):
        raise ValueError(f"{out / stage} is not empty (the import writes the stage whole): "
                         f"pass a new --out, or empty it")
    if (out / stage).exists() and not (out / stage).is_dir():
        raise ValueError(f"{out / stage} is a file, where the import writes the {stage} stage: "
                         f"pass a new --out")
    views = len(scene.image_paths)
    missing = [p for p in scene.image_paths if not p.is_file()]
    if missing:
        raise FileNotFoundError(f"image {missing[0]} does not exist ({len(missing)} of {views} "
                                "missing): pass --images DIR (COLMAP) or fix file_path "
                                "(nerfstudio)")
    if (near is None) != (far is None):
        raise ValueError("give both --near and --far, or neither (then the sparse points set "
                         "them)")
    if near is None:
        if scene.points is None or len(scene.points) == 0:
            raise ValueError(f"{scene.source} has no sparse 3D points to set near/far from: "
                             "give --near and --far (scene units)")
        near, far = near_far_from_points(scene.points, scene.extrinsics, scene.intrinsics)
    if not 0 < near < far or not math.isfinite(far):
        raise ValueError(f"near/far must satisfy 0 < near < far, got {near}, {far}")
    entry = standard_entry(views, context)

    images = [load_image(p, (int(s[0]), int(s[1])), resolution)
              for p, s in zip(scene.image_paths, scene.image_shapes)]
    shapes = {im.shape[:2] for im in images}
    if len(shapes) > 1:
        raise ValueError(f"the images of {scene.source} have different sizes "
                         f"{sorted(shapes)}: pass --image-shape H W")
    key = key or scene_key(scene.source)
    cameras = matrices_to_cameras(torch.from_numpy(scene.extrinsics),
                                  torch.from_numpy(scene.intrinsics))
    record = {"key": key, "url": str(scene.source), "cameras": cameras,
              "timestamps": torch.arange(views, dtype=torch.int64),
              "images": [encode_image(im, fmt) for im in images],
              "near_far": torch.tensor([near, far], dtype=torch.float32),
              "names": [p.name for p in scene.image_paths]}
    # All or nothing: the stage is written into a hidden folder and moved into place last,
    # after its evaluation index, so that an import killed at any point leaves either no stage
    # (a rerun starts afresh, removing what the killed one left) or the whole of it.
    partial = out / f".{stage}.partial"
    if partial.exists():
        shutil.rmtree(partial)
    with ChunkWriter(partial, stage) as writer:
        writer.add(record)
    # beside the stage's own metadata (the test stage's at the root, the train stage's in its
    # folder): a train-stage import into the root of a test one keeps the test stage's index
    index = metadata_folder(out, stage) / "evaluation_index_standard.json"
    inside_stage = index.parent == out / stage
    written = partial / stage / index.name if inside_stage else index
    remove_temporaries_of(written)  # what a killed import's write left
    write_json(written, {key: entry})
    os.replace(partial / stage, out / stage)  # an empty out/stage is replaced too
    partial.rmdir()
    h, w = images[0].shape[:2]
    return {"key": key, "views": views, "image_shape": [h, w], "near_far": [near, far],
            "stage_dir": str(out / stage), "evaluation_index": str(index),
            "context": entry["context"], "target": entry["target"]}
