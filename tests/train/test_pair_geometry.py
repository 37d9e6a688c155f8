"""train/studies/pair_geometry.py: on two cameras built from a known rotation and distance,
the pair's rotation and baseline over depth are the ones constructed, and a capture's depth is
the median camera-space z of the points in front of the camera."""

import importlib.util
import math
from pathlib import Path

import numpy as np

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "pair_geometry.py"
spec = importlib.util.spec_from_file_location("pair_geometry", SCRIPT)
study = importlib.util.module_from_spec(spec)
spec.loader.exec_module(study)


def rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    """Rodrigues' formula, written out here rather than taken from the script."""
    a = axis / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = math.radians(degrees)
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * k @ k


def test_constructed_pair():
    rng = np.random.default_rng(3)
    for degrees in (0.0, 7.5, 46.0, 95.0, 170.0):
        c2w = np.tile(np.eye(4), (2, 1, 1))
        c2w[0, :3, :3] = rotation(rng.normal(size=3), rng.uniform(0, 180))
        c2w[1, :3, :3] = c2w[0, :3, :3] @ rotation(rng.normal(size=3), degrees)
        c2w[0, :3, 3], c2w[1, :3, 3] = rng.normal(size=3), rng.normal(size=3)
        depth = np.array([2.0, 6.0])
        ratio, angle = study.pair_row(c2w, depth, 0, 1)
        # float64 throughout; arccos near 0 degrees loses precision to sqrt(eps) ~ 1e-8 rad,
        # so 1e-5 degrees bounds the rounding with room to spare
        assert abs(angle - degrees) < 1e-5
        assert math.isclose(ratio, np.linalg.norm(c2w[0, :3, 3] - c2w[1, :3, 3]) / 4.0,
                            rel_tol=1e-12)


def test_capture_depth_is_the_median_z_in_front(tmp_path, monkeypatch):
    # three cameras on the x axis looking down +z (OpenCV axes), points at z = 1..9 and two
    # behind the cameras, which must not count
    c2w = np.tile(np.eye(4), (3, 1, 1))
    c2w[:, 0, 3] = [0.0, 1.0, 3.0]
    points = np.array([[0, 0, z] for z in (1, 2, 3, 4, 9, -5, -6)], dtype=float)

    class Scene:
        extrinsics, points = c2w, None

    Scene.points = points
    monkeypatch.setattr(study, "read_cameras", lambda *a, **k: Scene)
    rows = study.capture_pairs(tmp_path, gaps=[1, 2], stride=1)
    # median of z in (1, 2, 3, 4, 9) is 3 for every camera: baselines 1, 2 and 3 over 3
    assert np.allclose([r[0] for r in rows], [1 / 3, 2 / 3, 3 / 3])
    assert np.allclose([r[1] for r in rows], 0.0, atol=1e-6)
