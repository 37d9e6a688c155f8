"""The view-dependence meter: the warp against an analytic scene (a textured plane seen by two
cameras, colour a smooth function of the world point), occlusion masking, and the per-class
bookkeeping on a record whose "glossy" half changes with the view."""

import math

import numpy as np
import pytest
import torch

from usplat_dr.data.chunks import encode_image, matrices_to_cameras
from usplat_dr.data.synth.render import GLOSSY, TEXTURED
from usplat_dr.evaluation.view_dependence import CLASSES, psnr_of, scene_errors, warp_into
from usplat_dr.geometry.cameras import pixel_directions

H, W = 40, 48
K = np.array([[0.9, 0, 0.5], [0, 0.9 * W / H, 0.5], [0, 0, 1]])
PLANE_Z = 5.0  # world plane z = 5, facing the cameras


def camera(x: float, yaw_deg: float) -> np.ndarray:
    """OpenCV camera-to-world at (x, 0, 0), turned by ``yaw_deg`` about +Y."""
    a = math.radians(yaw_deg)
    c2w = np.eye(4)
    c2w[:3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
    c2w[0, 3] = x
    return c2w


def colour(points: np.ndarray) -> np.ndarray:
    """A smooth texture on the plane: wavelength ~1.2 m, ~10 pixels at 5 m."""
    x, y = points[..., 0], points[..., 1]
    return np.stack([0.5 + 0.3 * np.sin(5 * x), 0.5 + 0.3 * np.cos(4 * y),
                     0.5 + 0.2 * np.sin(3 * x + 2 * y)], -1)


def view(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray-traced image and camera-space z of the plane (float64, exact)."""
    d_cam = pixel_directions(K, (H, W))
    d_world = d_cam @ c2w[:3, :3].T
    t = (PLANE_Z - c2w[2, 3]) / d_world[..., 2]  # along d_cam, whose z is 1: t is z
    return colour(c2w[:3, 3] + t[..., None] * d_world), t


def test_warp_reproduces_an_analytic_view():
    src, tgt = camera(0.4, -4.0), camera(0.0, 2.0)
    image_s, depth_s = view(src)
    image_t, depth_t = view(tgt)
    warped, valid = warp_into(depth_t, tgt, K, image_s, depth_s, src, K)
    assert valid.mean() > 0.7  # the frames overlap over most of the target
    # Bilinear reading of a sinusoid of ~10 px wavelength: error <= (pixel^2 / 8) |f''|
    # = (2 pi / 10)^2 / 8 * 0.3 ~ 0.015; a wrong convention (w2c for c2w, a half-pixel
    # shift of 0.5 px) moves the read point by >= 0.5 px: errors ~ 0.1.
    assert np.abs(warped - image_t)[valid].max() < 0.02
    # the same with the cameras' roles swapped (nothing is symmetric by accident)
    back, valid_b = warp_into(depth_s, src, K, image_t, depth_t, tgt, K)
    assert np.abs(back - image_s)[valid_b].max() < 0.02
    # with nothing occluded, co-visible = inside the source frame, projected here through
    # the inverted camera-to-world matrix (not the transpose the warp uses)
    points = np.concatenate([pixel_directions(K, (H, W)) * depth_t[..., None],
                             np.ones((H, W, 1))], -1) @ tgt.T
    cam = points @ np.linalg.inv(src).T
    u = (K[0, 0] * cam[..., 0] / cam[..., 2] + K[0, 2]) * W - 0.5
    v = (K[1, 1] * cam[..., 1] / cam[..., 2] + K[1, 2]) * H - 0.5
    inside = (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    assert 0 < (~inside).sum() and np.array_equal(valid, inside)


def test_occluded_points_are_masked():
    src, tgt = camera(0.5, 0.0), camera(0.0, 0.0)
    image_s, depth_s = view(src)
    image_t, depth_t = view(tgt)
    depth_s = depth_s.copy()
    depth_s[15:25, 20:30] = 2.0  # an occluder in front of the plane, in the source only
    warped, valid = warp_into(depth_t, tgt, K, image_s, depth_s, src, K)
    # target pixels whose plane point projects into the occluder's source pixels are hidden
    d_world = pixel_directions(K, (H, W))
    points = d_world * depth_t[..., None] - src[:3, 3]
    u = (K[0, 0] * points[..., 0] / points[..., 2] + K[0, 2]) * W - 0.5
    v = (K[1, 1] * points[..., 1] / points[..., 2] + K[1, 2]) * H - 0.5
    hidden = (u > 19) & (u < 30) & (v > 14) & (v < 25)
    assert hidden.sum() > 50 and not valid[hidden].any()
    assert np.abs(warped - image_t)[valid].max() < 0.02
    # a miss in the target (infinite depth) is never co-visible
    depth_t[0, 0] = np.inf
    assert not warp_into(depth_t, tgt, K, image_s, depth_s, src, K)[1][0, 0]


def test_scene_errors_split_by_material_class():
    # Three views of the plane; the right half of every view is "glossy" and brighter by 0.1
    # per view index (a change with the viewpoint), the left half matte. Warped matte pixels
    # match to the bilinear error and uint8 rounding (measured 34.5 dB); glossy ones are
    # off by exactly 0.1 from either context (20 dB, measured 20.2 with the same errors).
    cams = [camera(0.0, 0.0), camera(0.2, 0.0), camera(0.4, 0.0)]
    images, depths = [], []
    materials = np.full((3, H, W), TEXTURED, np.uint8)
    materials[:, :, W // 2:] = GLOSSY
    for i, c in enumerate(cams):
        im, d = view(c)
        im[:, W // 2:] += 0.1 * i - 0.1
        images.append((np.clip(im, 0, 1) * 255 + 0.5).astype(np.uint8))
        depths.append(d)
    k = torch.tensor(K, dtype=torch.float32).expand(3, 3, 3)
    record = {"cameras": matrices_to_cameras(torch.tensor(np.stack(cams)), k),
              "images": [encode_image(im, "png") for im in images],
              "depths": torch.tensor(np.stack(depths), dtype=torch.float16),
              "materials": torch.from_numpy(materials)}
    errs = scene_errors(record, {"context": [0, 2], "target": [1]})
    assert set(errs) == set(CLASSES) and errs["metal"][1] == 0
    matte, glossy = psnr_of(*errs["diffuse"]), psnr_of(*errs["glossy"])
    assert matte > 32 and 19.5 < glossy < 20.5, (matte, glossy)
    assert math.isnan(psnr_of(0.0, 0))


def test_psnr_of_is_the_mse_psnr():
    assert psnr_of(0.01 * 50, 50) == pytest.approx(20.0)


def test_noise_floor_of_a_rendered_set(tmp_path):
    # A tiny set at 2 spp: another sample seed gives another noisy image, so the floor is
    # finite; the class bookkeeping covers every pixel the maps name.
    pytest.importorskip("mitsuba")
    import json

    from usplat_dr.data.synth import synthesize
    from usplat_dr.evaluation.view_dependence import noise_floor

    synthesize(tmp_path, scenes=1, frames=6, resolution=(12, 12), seed=3, spp=2,
               progress=False, previews=0, kinds=("object",), appearance="view-dependent")
    index = json.loads((tmp_path / "evaluation_index_standard.json").read_text())
    floor = noise_floor(tmp_path, index, scenes=1, spp=2)
    covered = sum(c["pixels"] for c in floor.values())
    assert 0 < covered <= 12 * 12
    assert all(math.isfinite(c["psnr"]) for c in floor.values() if c["pixels"])
