"""The classical two-view plane sweep (``usplat_dr.geometry.plane_sweep``) against ground
truth: the Middlebury motorcycle's disparity (a real rectified pair, scikit-image) and a
synthetic scene's Mitsuba depth and renders."""

import numpy as np
import pytest
import skimage.data
import torch

from usplat_dr.data.shims import covering_size, cropped_intrinsics, rescale_and_crop
from usplat_dr.data.synth import render_spec
from usplat_dr.data.synth.scenes import make_spec
from usplat_dr.evaluation.metrics import psnr
from usplat_dr.geometry.plane_sweep import near_far_from_sweep, plane_sweep, sweep_render

#: skimage's calibration of the down-sampled pair (its docstring): f, cx, cy, doffs (px), B (m)
F, CX, CY, DOFFS, B = 994.978, 311.193, 254.877, 31.086, 0.193001


@pytest.fixture(scope="module")
def motorcycle():
    left, right, disp = skimage.data.stereo_motorcycle()
    h, w = left.shape[:2]
    k_l = np.array([[F / w, 0, CX / w], [0, F / h, CY / h], [0, 0, 1]])
    k_r = k_l.copy()
    k_r[0, 2] = (CX + DOFFS) / w  # the right camera's principal point: doffs further
    c2w_r = np.eye(4)
    c2w_r[0, 3] = B
    depth = F * B / (disp + DOFFS)  # Z = f B / (d + doffs); inf disparity: no ground truth
    return left, right, depth, k_l, k_r, c2w_r


def _at(size, motorcycle, move):
    left, right, depth, k_l, k_r, _ = motorcycle
    h, w = left.shape[:2]
    imgs = torch.from_numpy(np.stack([left, right])).permute(0, 3, 1, 2)
    small, _ = rescale_and_crop(imgs, torch.from_numpy(k_l)[None].repeat(2, 1, 1).float(),
                                (size, size), move)
    ks = [cropped_intrinsics(torch.from_numpy(k)[None], (h, w), (size, size), move)[0].numpy()
          for k in (k_l, k_r)]
    h_s, w_s = covering_size((h, w), (size, size))
    row, col = (h_s - size) // 2, (w_s - size) // 2
    ys = np.clip(((np.arange(size) + 0.5 + row) * h / h_s).astype(int), 0, h - 1)
    xs = np.clip(((np.arange(size) + 0.5 + col) * w / w_s).astype(int), 0, w - 1)
    a = small.permute(0, 2, 3, 1).double().numpy() / 255.0
    return a, ks, depth[np.ix_(ys, xs)]


def test_the_sweep_finds_the_motorcycles_depth_where_a_constant_cannot(motorcycle):
    *_, c2w_r = motorcycle
    hyp = 1.0 / np.linspace(1 / 1.5, 1 / 10.0, 128)
    absrel = {}
    for move in (True, False):
        a, ks, gt = _at(64, motorcycle, move)
        valid = np.isfinite(gt) & (gt > 0)
        d = plane_sweep(a[0], a[1], ks[0], ks[1], np.eye(4), c2w_r, hyp, window=7).depth
        absrel[move] = np.mean(np.abs(d[valid] - gt[valid]) / gt[valid])
    constant = np.mean(np.abs(np.median(gt[valid]) - gt[valid]) / gt[valid])
    # measured 2026-12-02 at 64x64: 0.125 with the principal point moved by the crop, 0.175
    # for the constant at the median; allowed 0.15 (a wrong baseline sign or a pixel-centre
    # slip gives 0.3 and more). Keeping the normalised cx (the field's shim) moves the left
    # and right rays apart by different amounts: 0.291, allowed anything above 0.125 + 0.05
    assert absrel[True] < 0.15 < constant - 0.01
    assert absrel[False] > absrel[True] + 0.05


def test_near_far_from_a_sweep_brackets_the_motorcycle(motorcycle):
    a, ks, gt = _at(96, motorcycle, True)
    near, far = near_far_from_sweep([a[0], a[1]], ks, [np.eye(4), motorcycle[-1]])
    g = gt[np.isfinite(gt) & (gt > 0)]
    lo, hi = np.percentile(g, [1, 99])
    # the truth's 1-99% range (2.17-4.66 m) inside: measured 1.52 / 7.64 (2026-12-02); allowed
    # within 3x of it (a range 10x too wide wastes the cost volume's depth planes)
    assert near < lo and far > hi
    assert near > lo / 3 and far < hi * 3


def test_a_classical_novel_view_beats_copying_on_a_synthetic_scene():
    # frames 0 and 2 of a photographic outdoor scene as context, frame 1 the target: measured
    # 2026-12-02 17.75 dB against copying's 14.68 (+3.1; +2.6 to +4.0 on the three kinds);
    # allowed: a margin of 1.5 dB (a depth that is always wrong renders below copying)
    spec = make_spec("outdoor", 3, 8, "photographic")
    imgs = render_spec(spec, (64, 64), spp=16, frames=[0, 1, 2])[0].astype(np.float64) / 255
    c2w = np.asarray(spec["cameras"]["c2w"])[:3]
    f = 0.5 / np.tan(np.radians(spec["cameras"]["fov_x_deg"]) / 2)
    k = np.array([[f, 0, 0.5], [0, f, 0.5], [0, 0, 1]])
    near, far = spec["near_far"]
    out = sweep_render([imgs[0], imgs[2]], [k, k], [c2w[0], c2w[2]], k, c2w[1], (64, 64),
                       1.0 / np.linspace(1 / near, 1 / far, 64))
    target = torch.from_numpy(imgs[1]).permute(2, 0, 1)
    nearest = 0 if (np.linalg.norm(c2w[1, :3, 3] - c2w[0, :3, 3])
                    <= np.linalg.norm(c2w[1, :3, 3] - c2w[2, :3, 3])) else 2
    copy = psnr(torch.from_numpy(imgs[nearest]).permute(2, 0, 1), target).item()
    assert psnr(torch.from_numpy(out).permute(2, 0, 1), target).item() > copy + 1.5
