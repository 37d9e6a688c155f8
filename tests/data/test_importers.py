"""``usplat import``: COLMAP (text, binary) and nerfstudio scenes written from a synthetic scene
with known cameras, imported, and compared with the truth; each convention pinned by a case
built by hand; the imported root read by the dataset and by the command line."""

import doctest
import json
import logging
import math
import struct

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from tests.data.fakes import random_poses, w2c_rows
from usplat_dr.cli import main
from usplat_dr.data import importers, read_chunk, read_index
from usplat_dr.data.chunks import decode_image
from usplat_dr.data.dataset import dataset_from_section
from usplat_dr.data.importers import (
    import_scene,
    qvec_to_rotation,
    read_colmap,
    read_nerfstudio,
    standard_entry,
)

H, W = 48, 64  # calibrated image size (non-square, so W/H swaps show)
V = 6
#: Two COLMAP cameras: PINHOLE (fx != fy, off-centre principal point, so swaps show) and
#: SIMPLE_PINHOLE. Pixels; images alternate between them.
CAMS = {1: ("PINHOLE", [50.0, 52.0, 31.5, 24.5]), 2: ("SIMPLE_PINHOLE", [55.0, 33.0, 23.0])}
DIST = 4.0  # cameras look at the origin from this distance; points fill the unit ball


def pixel_k(cam_id: int) -> np.ndarray:
    model, p = CAMS[cam_id]
    fx, fy, cx, cy = (p[0], p[1], p[2], p[3]) if model == "PINHOLE" else (p[0], p[0], p[1], p[2])
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


class Truth:
    """The synthetic scene: V cameras (random rotations from ``random_poses``, each looking at
    the origin from ``DIST``), 300 points in the unit ball, random PNG images."""

    def __init__(self, root):
        rng = np.random.default_rng(3)
        self.c2w = random_poses(V, rng)  # OpenCV camera-to-world
        self.c2w[:, :3, 3] = -DIST * self.c2w[:, :3, 2]  # centre = -DIST x forward (+Z)
        d = rng.normal(size=(300, 3))
        self.points = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.random((300, 1))
        self.cam_ids = [1 + i % 2 for i in range(V)]
        self.k_norm = np.stack([pixel_k(c) / [[W], [H], [1]] for c in self.cam_ids])
        self.names = [f"frame_{i:05d}.png" for i in range(V)]
        (root / "images").mkdir(parents=True)
        self.images = (rng.random((V, H, W, 3)) * 255).astype(np.uint8)
        for name, im in zip(self.names, self.images):
            Image.fromarray(im).save(root / "images" / name)
        self.root = root

    def rows(self) -> np.ndarray:
        """[V, 18] camera rows computed with numpy alone (independent of the importer)."""
        rows = np.zeros((V, 18))
        rows[:, 0], rows[:, 1] = self.k_norm[:, 0, 0], self.k_norm[:, 1, 1]
        rows[:, 2], rows[:, 3] = self.k_norm[:, 0, 2], self.k_norm[:, 1, 2]
        rows[:, 6:] = w2c_rows(self.c2w)
        return rows

    def depths(self) -> np.ndarray:
        """[V, N] camera-space z of every point in every view."""
        return np.stack([(np.c_[self.points, np.ones(len(self.points))]
                          @ np.linalg.inv(m).T)[:, 2] for m in self.c2w])

    def colmap_images(self):
        """(id, qvec w-first, tvec, camera id, name) per image, the quaternion from scipy
        (which stores x, y, z, w: reordered here), so the importer's own conversion is not
        used to make its input. Written in reverse order: the importer sorts by name."""
        for i in reversed(range(V)):
            w2c = np.linalg.inv(self.c2w[i])
            x, y, z, w = Rotation.from_matrix(w2c[:3, :3]).as_quat()
            yield i + 1, [w, x, y, z], w2c[:3, 3], self.cam_ids[i], self.names[i]

    def write_colmap_text(self, folder):
        folder.mkdir(parents=True)
        lines = ["# Camera list with one line of data per camera:"]
        lines += [f"{c} {m} {W} {H} " + " ".join(repr(x) for x in p) for c, (m, p) in
                  CAMS.items()]
        (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
        lines = ["# Image list with two lines of data per image:"]
        for i, q, t, c, name in self.colmap_images():
            pose = " ".join(repr(float(x)) for x in [*q, *t])
            lines.append(f"{i} {pose} {c} {name}")
            lines.append("" if i % 2 else "10.5 20.5 1 11.5 21.5 -1")  # 2D points: unused
        (folder / "images.txt").write_text("\n".join(lines) + "\n")
        lines = ["# 3D point list with one line of data per point:"]
        lines += [f"{j + 1} {x!r} {y!r} {z!r} 128 128 128 0.5 1 0 2 0"
                  for j, (x, y, z) in enumerate(self.points.tolist())]
        (folder / "points3D.txt").write_text("\n".join(lines) + "\n")
        return folder

    def write_colmap_binary(self, folder):
        folder.mkdir(parents=True)
        ids = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1}
        data = struct.pack("<Q", len(CAMS))
        for c, (m, p) in CAMS.items():
            data += struct.pack("<iiQQ", c, ids[m], W, H) + struct.pack(f"<{len(p)}d", *p)
        (folder / "cameras.bin").write_bytes(data)
        data = struct.pack("<Q", V)
        for i, q, t, c, name in self.colmap_images():
            data += struct.pack("<idddddddi", i, *q, *t, c) + name.encode() + b"\0"
            data += struct.pack("<Q", 2) + struct.pack("<ddqddq", 1.5, 2.5, 7, 3.5, 4.5, -1)
        (folder / "images.bin").write_bytes(data)
        data = struct.pack("<Q", len(self.points))
        for j, (x, y, z) in enumerate(self.points.tolist()):
            data += struct.pack("<QdddBBBd", j + 1, x, y, z, 1, 2, 3, 0.25)
            data += struct.pack("<Q", 1) + struct.pack("<ii", 1, 0)
        (folder / "points3D.bin").write_bytes(data)
        return folder

    def write_nerfstudio(self):
        """transforms.json beside images/: OpenGL camera-to-world, camera 1's intrinsics at
        the top level, camera 2's per frame; frames in shuffled order."""
        k1 = pixel_k(1)
        meta = {"camera_model": "OPENCV", "w": W, "h": H, "fl_x": k1[0, 0], "fl_y": k1[1, 1],
                "cx": k1[0, 2], "cy": k1[1, 2], "k1": 0.0, "p1": 0.0,
                "applied_transform": np.eye(4)[:3].tolist(), "frames": []}
        for i in [3, 0, 5, 1, 4, 2]:
            frame = {"file_path": f"images/{self.names[i]}",
                     # OpenCV -> OpenGL camera axes: flip y and z (written here, not taken
                     # from the importer, so a wrong flip there cannot cancel out)
                     "transform_matrix": (self.c2w[i] @ np.diag([1, -1, -1, 1])).tolist()}
            if self.cam_ids[i] == 2:
                k = pixel_k(2)
                frame.update(fl_x=k[0, 0], fl_y=k[1, 1], cx=k[0, 2], cy=k[1, 2])
            meta["frames"].append(frame)
        (self.root / "transforms.json").write_text(json.dumps(meta))
        return self.root


@pytest.fixture(scope="module")
def truth(tmp_path_factory):
    t = Truth(tmp_path_factory.mktemp("scene"))
    t.write_colmap_text(t.root / "sparse_txt" / "0")
    t.write_colmap_binary(t.root / "sparse" / "0")
    t.write_nerfstudio()
    return t


def only_record(root, stage="test"):
    [chunk] = sorted((root / stage).glob("*.torch"))
    [record] = read_chunk(chunk)
    assert read_index(root / stage) == {record["key"]: chunk.name}
    return record


# ---- The readers against the truth ----


@pytest.mark.parametrize("model", ["sparse_txt/0", "sparse/0"])
def test_colmap_cameras_equal_the_truth(truth, model):
    scene = read_colmap(truth.root / model)
    assert [p.name for p in scene.image_paths] == truth.names  # sorted by name
    # float64 throughout; 1e-9 absorbs one inverse of a rotation about 4 units from the origin
    np.testing.assert_allclose(scene.extrinsics, truth.c2w, atol=1e-9)
    np.testing.assert_allclose(scene.intrinsics, truth.k_norm, atol=1e-12)  # one division
    np.testing.assert_allclose(scene.points, truth.points, atol=0)  # repr/struct: exact
    assert scene.image_shapes.tolist() == [[H, W]] * V


def test_nerfstudio_cameras_equal_the_truth(truth):
    scene = read_nerfstudio(truth.root)
    assert [p.name for p in scene.image_paths] == truth.names  # sorted, not file order
    # the JSON holds float64 repr: the axis flip is exact
    np.testing.assert_allclose(scene.extrinsics, truth.c2w, atol=1e-12)
    np.testing.assert_allclose(scene.intrinsics, truth.k_norm, atol=1e-12)
    assert scene.points is None


def test_text_and_binary_colmap_give_identical_chunks(truth, tmp_path):
    for name, model in (("txt", "sparse_txt/0"), ("bin", "sparse/0")):
        import_scene(read_colmap(truth.root / model), tmp_path / name, key="s")
    a, b = only_record(tmp_path / "txt"), only_record(tmp_path / "bin")
    assert a.keys() == b.keys()
    for k in a:
        if k == "url":  # the source folder
            continue
        if k == "images":
            assert all(torch.equal(x, y) for x, y in zip(a[k], b[k]))
        elif isinstance(a[k], torch.Tensor):
            assert torch.equal(a[k], b[k]), k  # bit for bit: both hold the same float64s
        else:
            assert a[k] == b[k], k


@pytest.mark.parametrize("source", ["colmap", "nerfstudio"])
def test_imported_chunk_holds_the_true_cameras_and_images(truth, tmp_path, source):
    scene = (read_colmap(truth.root / "sparse/0") if source == "colmap"
             else read_nerfstudio(truth.root))
    summary = import_scene(scene, tmp_path, near=1.0, far=10.0)
    record = only_record(tmp_path)
    # float32 rows: entries up to |4| round to ~5e-7; 1e-5 is the brief's bound
    np.testing.assert_allclose(record["cameras"].double().numpy(), truth.rows(), atol=1e-5)
    for im, ref in zip(record["images"], truth.images):  # PNG, no resize: exact
        assert torch.equal(decode_image(im), torch.from_numpy(ref).permute(2, 0, 1))
    assert record["timestamps"].tolist() == list(range(V))
    assert record["names"] == truth.names
    assert summary["near_far"] == [1.0, 10.0] and record["near_far"].tolist() == [1.0, 10.0]
    index = json.loads((tmp_path / "evaluation_index_standard.json").read_text())
    assert index == {record["key"]: standard_entry(V)} == {
        record["key"]: {"context": [1, 3], "target": [2]}}


def test_resize_keeps_normalised_intrinsics(truth, tmp_path):
    # A non-uniform resize (48x64 -> 24x40: x0.5 rows, x0.625 columns): pixel intrinsics scale
    # per axis, so fx/W, cx/W, fy/H, cy/H do not change.
    import_scene(read_colmap(truth.root / "sparse/0"), tmp_path, resolution=(24, 40))
    record = only_record(tmp_path)
    assert decode_image(record["images"][0]).shape == (3, 24, 40)
    np.testing.assert_allclose(record["cameras"][:, :4].double().numpy(), truth.rows()[:, :4],
                               atol=1e-7)  # float32 of numbers below 1.1: 1e-7 relative
    # A point projects to the same image fraction before and after: pixel u at 64 wide is
    # u * 40 / 64 at 40 wide, which the stored normalised K gives.
    p = np.array([0.2, -0.1, 0.3, 1.0])
    cam = np.linalg.inv(truth.c2w[0]) @ p
    u_orig = (pixel_k(1) @ cam[:3] / cam[2])[0]
    k = record["cameras"][0].double().numpy()
    assert math.isclose((k[0] * cam[0] / cam[2] + k[2]) * 40, u_orig * 40 / W, rel_tol=1e-6)


def test_near_far_bracket_the_true_point_depths(truth, tmp_path):
    summary = import_scene(read_colmap(truth.root / "sparse/0"), tmp_path)
    near, far = summary["near_far"]
    depths = truth.depths()
    assert 0 < near <= depths.min() and depths.max() <= far
    # and no wider than the margins: percentiles lie within [min, max], times 0.8 and 1.2
    assert near >= 0.8 * depths.min() and far <= 1.2 * depths.max()


def test_dataset_reads_the_imported_root(truth, tmp_path):
    # The end-to-end check: eval and render load data through dataset_from_section.
    summary = import_scene(read_colmap(truth.root / "sparse/0"), tmp_path, resolution=(32, 48))
    ds = dataset_from_section({"name": "synth", "roots": [tmp_path], "image_shape": [32, 48],
                               "evaluation_index": summary["evaluation_index"]}, "test")
    [example] = list(ds)
    ctx = example["context"]
    assert ctx["index"].tolist() == [1, 3] and example["target"]["index"].tolist() == [2]
    assert ctx["image"].shape == (2, 3, 32, 48)
    # float32 poses inverted twice (chunk w2c, loader c2w): ~1e-6 at 4 units
    np.testing.assert_allclose(ctx["extrinsics"].double().numpy(), truth.c2w[[1, 3]],
                               atol=1e-5)
    assert math.isclose(ctx["near"][0].item(), summary["near_far"][0], rel_tol=1e-6)


# ---- Each convention, on a case built by hand ----


def test_quaternion_order_is_w_x_y_z():
    # (w, x, y, z) = (cos 45, 0, 0, sin 45): +90 degrees about z, x -> y
    s = math.sqrt(0.5)
    np.testing.assert_allclose(qvec_to_rotation(np.array([s, 0, 0, s])),
                               [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    q = Rotation.random(5, random_state=0)  # scipy stores x, y, z, w
    for xyzw, m in zip(q.as_quat(), q.as_matrix()):
        # 1e-12: float64 products of unit quaternion components
        np.testing.assert_allclose(qvec_to_rotation(np.roll(xyzw, 1)), m, atol=1e-12)


def write_one_camera_colmap(folder, model="PINHOLE", params=(50.0, 50.0, 32.0, 24.0),
                            pose="1 0 0 0 0 0 5"):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cameras.txt").write_text(f"1 {model} 64 48 {' '.join(map(str, params))}\n")
    (folder / "images.txt").write_text(f"1 {pose} 1 a.png\n\n")
    (folder / "images").mkdir(exist_ok=True)
    Image.new("RGB", (64, 48)).save(folder / "images" / "a.png")
    return folder


def test_colmap_pose_is_world_to_camera(tmp_path):
    # identity rotation, tvec (0, 0, 5): x_cam = x_world + t, so the camera centre is at
    # z = -5 (c2w translation = -R^T t), looking down +z
    scene = read_colmap(write_one_camera_colmap(tmp_path))
    np.testing.assert_allclose(scene.extrinsics[0, :3, 3], [0, 0, -5])
    np.testing.assert_allclose(scene.intrinsics[0], [[50 / 64, 0, 0.5], [0, 50 / 48, 0.5],
                                                     [0, 0, 1]])  # pixels / (W, H)


def test_nerfstudio_opengl_axes_become_opencv(tmp_path):
    # An OpenGL camera at the origin with the identity matrix looks down -Z with +Y up: in
    # OpenCV axes its forward (+Z column) is world -Z and its down (+Y column) is world -Y.
    Image.new("RGB", (8, 6)).save(tmp_path / "a.png")
    (tmp_path / "transforms.json").write_text(json.dumps({
        "fl_x": 4, "fl_y": 4, "cx": 4, "cy": 3, "w": 8, "h": 6,
        "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}]}))
    c2w = read_nerfstudio(tmp_path).extrinsics[0]
    np.testing.assert_array_equal(c2w[:3, 2], [0, 0, -1])
    np.testing.assert_array_equal(c2w[:3, 1], [0, -1, 0])
    np.testing.assert_array_equal(c2w[:3, 0], [1, 0, 0])


def test_distorted_models_are_refused_or_dropped_with_a_warning(tmp_path, caplog):
    folder = write_one_camera_colmap(tmp_path, "OPENCV", (50, 52, 32, 24, 0.1, 0, 0, 0))
    with pytest.raises(ValueError, match="OPENCV has distortion.*--ignore-distortion"):
        read_colmap(folder)
    with caplog.at_level(logging.WARNING, logger="usplat_dr.data.importers"):
        scene = read_colmap(folder, ignore_distortion=True)
    assert "dropping the OPENCV distortion" in caplog.text
    np.testing.assert_allclose(scene.intrinsics[0, 0, 0], 50 / 64)
    zero = write_one_camera_colmap(tmp_path / "z", "SIMPLE_RADIAL", (50, 32, 24, 0.0))
    assert read_colmap(zero).intrinsics[0, 0, 0] == 50 / 64  # zero distortion: a pinhole
    fisheye = write_one_camera_colmap(tmp_path / "f", "OPENCV_FISHEYE", (50,) * 8)
    with pytest.raises(ValueError, match="OPENCV_FISHEYE is not supported.*image_undistorter"):
        read_colmap(fisheye, ignore_distortion=True)


def test_without_points_near_far_are_required(truth, tmp_path):
    with pytest.raises(ValueError, match="no sparse 3D points.*--near and --far"):
        import_scene(read_nerfstudio(truth.root), tmp_path)


def test_doctests_run():
    result = doctest.testmod(importers)
    assert result.attempted > 0 and result.failed == 0


# ---- The command ----


def test_usplat_import_command(truth, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["-q", "import", "--colmap", str(truth.root / "sparse" / "0"), "--out",
                 str(out), "--image-shape", "24", "32", "--key", "mine", "--context", "0",
                 "5", "--format", "jpeg"]) == 0
    assert "imported 6 views of 'mine'" in capsys.readouterr().out
    record = only_record(out)
    assert record["key"] == "mine" and decode_image(record["images"][0]).shape == (3, 24, 32)
    index = json.loads((out / "evaluation_index_standard.json").read_text())
    # synth's rule: 4 frames between -> positions 0.75, 1.5, 2.25 rounded (half to even),
    # so frames 2 and 3 (the repeat collapses)
    assert index == {"mine": {"context": [0, 5], "target": [2, 3]}}
    # writing into the same root again is refused, not merged
    assert main(["-q", "import", "--colmap", str(truth.root / "sparse" / "0"), "--out",
                 str(out)]) == 2
    assert "already holds a dataset" in capsys.readouterr().err


@pytest.mark.parametrize("case, needle", [
    ("no_cameras", "cameras.bin (or cameras.txt) does not exist"),
    ("unknown_model", "unknown camera model 'WEIRD'"),
    ("missing_image", "a.png does not exist"),
    ("no_transforms", "transforms.json does not exist"),
])
def test_user_mistakes_end_in_one_line(tmp_path, capsys, case, needle):
    folder = write_one_camera_colmap(tmp_path / "m")
    source = ["--colmap", str(folder)]
    if case == "no_cameras":
        (folder / "cameras.txt").unlink()
    elif case == "unknown_model":
        (folder / "cameras.txt").write_text("1 WEIRD 64 48 50\n")
    elif case == "missing_image":
        (folder / "images" / "a.png").unlink()
    else:
        source = ["--nerfstudio", str(folder)]
    assert main(["-q", "import", *source, "--out", str(tmp_path / "out"), "--near", "1",
                 "--far", "9"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("usplat import: error: ") and needle in err, err
    assert len(err.splitlines()) == 1, err
