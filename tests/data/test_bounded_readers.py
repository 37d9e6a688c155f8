"""The camera readers read what a file holds and what its counts allow, never the size a
file claims: sparse files of 1 GiB (4 kB on disk) under a 4 GiB address-space limit, counts
past ``MAX_CAMERAS``, absurd sizes and focal lengths, one image named twice. Each is refused
with a message naming the file (or read, where the file is valid), in bounded memory."""

import json
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from usplat_dr.data import importers
from usplat_dr.data.importers import (
    MAX_CAMERAS,
    read_colmap_cameras_binary,
    read_colmap_cameras_text,
    read_colmap_images_binary,
    read_nerfstudio,
)
from usplat_dr.io.user_files import read_bytes

GIB = 2**30


def sparse(path: Path, head: bytes, size: int = GIB) -> Path:
    """``head`` followed by zeros up to ``size`` bytes, as a sparse file (the zeros take no
    disk)."""
    with open(path, "wb") as f:
        f.write(head)
        f.truncate(size)
    return path


def under_limit(code: str, limit: int = 4 * GIB) -> subprocess.CompletedProcess:
    """``code`` run in a fresh Python with its address space capped at ``limit`` once the
    imports are done (torch's import reserves more address space than it uses)."""
    program = textwrap.dedent(f"""
        import resource
        import usplat_dr.data.importers as importers
        from usplat_dr.io.user_files import read_bytes
        resource.setrlimit(resource.RLIMIT_AS, ({limit}, {limit}))
        """) + textwrap.dedent(code)
    return subprocess.run([sys.executable, "-c", program], capture_output=True, text=True,
                          timeout=120, check=False)


@pytest.mark.parametrize("name, head, message", [
    # a count of 0 and a gibibyte of zeros after it: not a model, refused at its end
    ("cameras.bin", struct.pack("<Q", 0), "bytes after its last record"),
    ("images.bin", struct.pack("<Q", 0), "bytes after its last record"),
    # a count of 2^40 images: refused by the count before any record is read
    ("images.bin", struct.pack("<Q", 2**40), "more than the 100,000 a camera file may hold"),
    ("points3D.bin", struct.pack("<Q", 2**40), "points, more than its"),
    # one endless line of zeros: stopped at the first line's bound
    ("images.txt", b"", "a line longer than"),
    ("cameras.txt", b"# a comment\n", "a line longer than"),
])
def test_a_sparse_gibibyte_is_refused_in_bounded_memory(tmp_path, name, head, message):
    path = sparse(tmp_path / name, head)
    reader = {"cameras.bin": "read_colmap_cameras_binary", "images.bin":
              "read_colmap_images_binary", "points3D.bin": "read_colmap_points_binary",
              "images.txt": "read_colmap_images_text",
              "cameras.txt": "read_colmap_cameras_text"}[name]
    # 1 GiB read whole would need more than the 1.5 GiB left above the imports' use of the
    # 4 GiB; the readers stream, so a refusal comes back as a message, not a MemoryError
    proc = under_limit(f"""
        from pathlib import Path
        try:
            importers.{reader}(Path({str(path)!r}))
        except ValueError as e:
            print("refused:", e)
        """)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "refused:" in proc.stdout and message in proc.stdout and str(path) in proc.stdout


def test_a_small_file_is_read_under_a_memory_limit_whatever_its_bound(tmp_path):
    # read_bytes asked the file for its maximum (4 GiB for a PLY) at once: a MemoryError
    # under any limit below that, for a 10 kB file
    path = tmp_path / "small.bin"
    path.write_bytes(bytes(range(256)) * 40)
    proc = under_limit(f"""
        data = read_bytes({str(path)!r}, "PLY file", 4 * 2**30)
        print(len(data), data[:3].hex())
        """, limit=GIB + GIB // 2)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["10240", "000102"]
    assert read_bytes(path, "x") == path.read_bytes()


def colmap_camera(model_id: int, width: int, height: int, params) -> bytes:
    return struct.pack("<iiQQ", 1, model_id, width, height) + struct.pack(
        f"<{len(params)}d", *params)


def test_a_valid_binary_model_still_reads(tmp_path):
    path = tmp_path / "cameras.bin"
    path.write_bytes(struct.pack("<Q", 1) + colmap_camera(1, 640, 480, [500, 500, 320, 240]))
    cams = read_colmap_cameras_binary(path)
    assert cams[1].width == 640 and cams[1].params.tolist() == [500, 500, 320, 240]
    images = tmp_path / "images.bin"
    record = struct.pack("<idddddddi", 7, 1, 0, 0, 0, 0, 0, 0, 1) + b"a.png\0"
    images.write_bytes(struct.pack("<Q", 1) + record + struct.pack("<Q", 1)
                       + struct.pack("<ddq", 1.0, 2.0, -1))
    assert read_colmap_images_binary(images)[7][3] == "a.png"
    images.write_bytes(images.read_bytes()[:-4])  # a truncated point
    with pytest.raises(ValueError, match="ends early"):
        read_colmap_images_binary(images)


@pytest.mark.parametrize("width, height, params, message", [
    (0, 480, [500, 500, 320, 240], "the image size must be whole pixels in 1..65,536"),
    (10**9, 480, [500, 500, 320, 240], "the image size must be whole pixels"),
    (640, 480, [1e300, 500, 320, 240], "the focal lengths must be in"),
    (640, 480, [500, -1, 320, 240], "the focal lengths must be in"),
    (640, 480, [500, 500, float("nan"), 240], "finite parameters"),
])
def test_absurd_cameras_are_refused_naming_the_camera_file(tmp_path, width, height, params,
                                                          message):
    path = tmp_path / "cameras.bin"
    path.write_bytes(struct.pack("<Q", 1) + colmap_camera(1, width, height, params))
    with pytest.raises(ValueError, match=message) as e:
        read_colmap_cameras_binary(path)
    assert str(path) in str(e.value) and "camera 1" in str(e.value)  # cameras.bin, not images
    text = tmp_path / "cameras.txt"
    text.write_text(f"1 PINHOLE {width} {height} {' '.join(map(str, params))}\n")
    with pytest.raises(ValueError, match=message):
        read_colmap_cameras_text(text)


def transforms(folder: Path, frames, **top) -> Path:
    folder.mkdir(exist_ok=True)
    meta = {"fl_x": 50.0, "w": 64, "h": 64, **top, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def frame(name: str, x: float = 0.0) -> dict:
    m = np.eye(4)
    m[0, 3] = x
    return {"file_path": name, "transform_matrix": m.tolist()}


def test_a_transforms_json_with_absurd_cameras_or_counts_is_refused(tmp_path):
    folder = transforms(tmp_path / "a", [frame("a.png"), frame("b.png", 1.0)], w=1e300,
                        h=1e300)
    with pytest.raises(ValueError, match=r"transforms.json frame 'a.png': the camera: the "
                                         r"image size must be whole pixels"):
        read_nerfstudio(folder)
    folder = transforms(tmp_path / "b", [frame("a.png"), frame("b.png", 1.0)], fl_x=1e9)
    with pytest.raises(ValueError, match="the focal lengths must be in"):
        read_nerfstudio(folder)
    # a million frames naming one image: refused by the count, before any frame is read
    folder = transforms(tmp_path / "c", [{}] * (MAX_CAMERAS * 10))
    with pytest.raises(ValueError, match="declares 1,000,000 frames, more than the 100,000"):
        read_nerfstudio(folder)


def test_one_image_named_twice_is_refused_naming_it(tmp_path):
    folder = transforms(tmp_path / "d", [frame("a.png"), frame("./a.png", 1.0),
                                         frame("b.png", 2.0)])
    with pytest.raises(ValueError, match=r"frames name the image .*a\.png twice"):
        read_nerfstudio(folder)
    assert len(read_nerfstudio(transforms(tmp_path / "e", [frame("a.png"),
                                                           frame("b.png", 1.0)])).image_paths) == 2


def test_the_bounds_are_the_documented_ones():
    assert importers.MAX_CAMERAS == 100_000 and importers.MAX_IMAGE_SIDE == 65_536
    assert importers.MAX_FOCAL == 1e6


def test_a_ply_claiming_a_gibibyte_is_read_to_its_vertices_end(tmp_path):
    # a valid 3DGS PLY of 50 Gaussians followed by a sparse gibibyte: only the header and
    # the 50 vertices it declares are read, under a limit a whole read would break
    from tests.model.test_ply import random_gaussians
    from usplat_dr.model.ply import write_ply

    path = write_ply(tmp_path / "g.ply", random_gaussians(50))
    size = path.stat().st_size
    with open(path, "r+b") as f:
        f.truncate(GIB)
    proc = under_limit(f"""
        from usplat_dr.model.ply import read_ply
        g = read_ply({str(path)!r})
        print(len(g["means"]), g["sh_degree"])
        """, limit=GIB + GIB // 2)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["50", "3"]
    with open(path, "r+b") as f:  # and cut short, it says how much is missing
        f.truncate(size - 10)
    from usplat_dr.model.ply import read_ply
    with pytest.raises(ValueError, match="truncated: the header declares 50 vertices"):
        read_ply(path)


def test_a_camera_path_may_repeat_a_placeholder_image(tmp_path):
    # a --path file's frames name no image that is read: the same placeholder is fine there,
    # and the pixel size may be written as text, as a JSON writer may
    from usplat_dr.data.user_views import read_cameras

    folder = transforms(tmp_path / "path", [frame("t"), frame("t", 1.0), frame("t", 2.0)],
                        w="64", h="64")
    scene = read_cameras(folder / "transforms.json", what="--path")
    assert len(scene.extrinsics) == 3
    with pytest.raises(ValueError, match="twice"):
        read_cameras(folder / "transforms.json")
