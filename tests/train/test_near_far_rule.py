"""train/studies/near_far_rule.py: its default rule is the importer's, and the points it makes
lie on the surfaces the depth maps describe."""

import importlib.util
from pathlib import Path

import numpy as np
import torch

from usplat_dr.data.chunks import matrices_to_cameras
from usplat_dr.data.importers import near_far_from_points

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "near_far_rule.py"
spec = importlib.util.spec_from_file_location("near_far_rule", SCRIPT)
rule = importlib.util.module_from_spec(spec)
spec.loader.exec_module(rule)


def test_the_default_rule_is_the_importers():
    pts = np.random.default_rng(0).normal(size=(500, 3)) + [0, 0, 5]
    k = np.array([[[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1]]])
    got = rule.rule_range(pts, np.eye(4)[None], k, rule.RULES["p1-99 x0.8/1.2"])
    # the importer rounds to 6 decimals
    np.testing.assert_allclose(got, near_far_from_points(pts, np.eye(4)[None], k), atol=1e-6)


def test_points_project_back_to_their_pixels_at_the_true_depth():
    # one camera at (1, 2, 3) looking down +z, a plane of depth 4 everywhere: every point
    # must be 4 in front of the camera and inside its image
    c2w = torch.eye(4)[None]
    c2w[0, :3, 3] = torch.tensor([1.0, 2.0, 3.0])
    k = torch.tensor([[[0.8, 0, 0.5], [0, 0.9, 0.5], [0, 0, 1]]])
    scene = {"cameras": matrices_to_cameras(c2w, k), "depths": torch.full((1, 6, 8), 4.0)}
    pts = rule.sfm_points(scene, 20, np.random.default_rng(1))
    cam = pts - [1.0, 2.0, 3.0]
    np.testing.assert_allclose(cam[:, 2], 4.0, atol=1e-6)  # float32 camera rows
    u, v = 0.8 * cam[:, 0] / cam[:, 2] + 0.5, 0.9 * cam[:, 1] / cam[:, 2] + 0.5
    # pixel centres of an 8x6 image: u in (0.5/8 .. 7.5/8), v in (0.5/6 .. 5.5/6)
    np.testing.assert_allclose(np.sort(np.unique(np.round(u * 8 - 0.5, 4))) % 1, 0, atol=1e-3)
    assert u.min() > 0 and u.max() < 1 and v.min() > 0 and v.max() < 1
