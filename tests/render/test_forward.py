"""Forward agreement of the rasteriser with the dense float64 reference
(``usplat_dr.render.reference``).

Tolerances: float32 against float64. Colour and alpha are sums of <= ~100 weighted terms of
size <= 1 (observed errors ~5e-7); 1e-5 leaves 20x margin while a wrong rule (a missed skip, a
half-pixel shift, a wrong stop) changes pixels by >= 1/255 ~ 4e-3. Depth is the same sum weighted
by z, so its tolerance scales with the largest depth.
"""

import math

import pytest
import torch

from tests.render.helpers import max_err, render_both
from usplat_dr.render import RasterSettings, rasterize
from usplat_dr.render.reference import render_ref
from usplat_dr.render.scenes import (
    GaussianScene,
    covariances_from,
    pixel_aligned_scene,
    random_rotations,
    random_scene,
)

ATOL = 1e-5


def assert_matches(ours, ref, depth_scale=10.0, atol=ATOL):
    c, a, d = max_err(ours, ref)
    assert c <= atol and a <= atol, (c, a)
    assert d <= atol * depth_scale, d
    for t in (ours.color, ours.alpha, ours.depth):
        assert torch.isfinite(t).all()


@pytest.mark.parametrize("shape", [(32, 32), (24, 40), (17, 5), (1, 1)])
@pytest.mark.parametrize("sh_degree", [0, 1, 3, 4])
def test_random_scene(device, shape, sh_degree):
    scene = random_scene(150, *shape, batch=2, seed=sh_degree, sh_degree=sh_degree)
    ours, ref = render_both(scene, device)
    assert_matches(ours, ref)


def test_pixel_aligned_scene(device):
    # 2 H W Gaussians unprojected from two views at random depths, rendered from a third camera.
    ours, ref = render_both(pixel_aligned_scene(24, 32, seed=3), device)
    assert_matches(ours, ref)
    assert ours.alpha.mean() > 0.9  # the scene really covers the image


def test_high_opacity_exercises_clamp_and_early_stop(device):
    scene = random_scene(200, 24, 40, seed=2, opacity_range=(0.9, 1.0), scale_range=(0.1, 0.5))
    ours, ref = render_both(scene, device)
    assert_matches(ours, ref)
    # The 0.99 clamp and the T < 1e-4 stop are both active in this scene.
    assert (ours.alpha > 1 - 1e-3).float().mean() > 0.1


def test_mvsplat_basis_with_degree_4(device):
    scene = random_scene(120, 24, 24, seed=7, sh_degree=4)
    ours, ref = render_both(scene, device, settings=RasterSettings(sh_basis="mvsplat"),
                            basis="mvsplat")
    assert_matches(ours, ref)
    other = rasterize(*scene.to(device=device).args())
    assert (other.color - ours.color).abs().max() > 1e-3  # the two bases really differ here


def test_off_centre_principal_point(device):
    scene = random_scene(150, 20, 28, seed=11)
    scene.intrinsics[:, 0, 2] = 0.3
    scene.intrinsics[:, 1, 2] = 0.65
    ours, ref = render_both(scene, device)
    assert_matches(ours, ref)


def render_cuda_intrinsics(intrinsics: torch.Tensor) -> torch.Tensor:
    """The camera ``render_cuda`` (pixelSplat/MVSplat) really renders with, in float64,
    written from its code: ``get_fov`` unprojects the edge midpoints (0, 0.5), (1, 0.5),
    (0.5, 0), (0.5, 1) with ``K^-1``, takes the angles between the normalised rays
    (``acos``), and the rasteriser uses ``focal = size / (2 tan(fov / 2))`` with the
    principal point at the image centre (its symmetric projection matrix)."""
    k_inv = torch.linalg.inv(intrinsics.double())

    def unit(u, v):
        r = k_inv @ torch.tensor([u, v, 1.0], dtype=torch.float64)
        return r / r.norm(dim=-1, keepdim=True)

    fov_x = (unit(0, 0.5) * unit(1, 0.5)).sum(-1).acos()
    fov_y = (unit(0.5, 0) * unit(0.5, 1)).sum(-1).acos()
    out = torch.zeros_like(k_inv)
    out[:, 0, 0] = 0.5 / (0.5 * fov_x).tan()  # normalised: (W / (2 tan)) / W
    out[:, 1, 1] = 0.5 / (0.5 * fov_y).tan()
    out[:, 0, 2] = out[:, 1, 2] = 0.5
    out[:, 2, 2] = 1
    return out


def test_render_cuda_projection_ignores_the_principal_point_as_render_cuda_does(device):
    scene = random_scene(150, 20, 28, batch=2, seed=12)
    scene.intrinsics[:, 0, 2] = torch.tensor([0.3, 0.55])
    scene.intrinsics[:, 1, 2] = torch.tensor([0.65, 0.45])
    scene.intrinsics[1, 0, 1] = 0.05  # skew: get_fov's K^-1 sees it (our projection does not)
    settings = RasterSettings(projection="render_cuda")
    ours = rasterize(*scene.to(device=device).args(), settings=settings)
    symmetric = scene.to(dtype=torch.float64)
    symmetric.intrinsics = render_cuda_intrinsics(scene.intrinsics)
    assert_matches(ours, render_ref(*symmetric.args()))
    # ... and it really differs from the projection that honours cx, cy
    exact = rasterize(*scene.to(device=device).args())
    assert (exact.color - ours.color).abs().max() > 1e-2


def test_render_cuda_projection_equals_intrinsics_for_a_centred_camera(device):
    scene = random_scene(150, 20, 28, seed=13)  # cx = cy = 0.5, no skew
    a = rasterize(*scene.to(device=device).args(),
                  settings=RasterSettings(projection="render_cuda"))
    b = rasterize(*scene.to(device=device).args())
    # fx from tan(atan(0.5 / fx)): float32 rounding of the focal length, ~1e-7 relative
    assert (a.color - b.color).abs().max() <= 1e-5 and (a.alpha - b.alpha).abs().max() <= 1e-5


def test_follows_the_16x16_tile_cut(device):
    # Large, faint Gaussians reach alpha >= 1/255 beyond 3 sigma, where the reference's tile cut
    # drops them: the cut changes the image, and we follow it.
    scene = random_scene(60, 40, 40, seed=4, opacity_range=(0.8, 0.95), scale_range=(0.05, 0.1))
    ours, ref = render_both(scene, device)
    assert_matches(ours, ref)
    no_cut = render_both(scene, device, tile_cut=False)[1]
    assert (no_cut[0] - ref[0]).abs().max() > 1e-3


@pytest.mark.parametrize("settings", [
    RasterSettings(tile_size=4), RasterSettings(tile_size=8), RasterSettings(tile_size=16),
    RasterSettings(tile_size=4, opacity_cull=False),
    RasterSettings(tile_size=8, opacity_cull=False),
])
def test_every_tiling_renders_the_reference_function_bit_for_bit(device, settings):
    # Smaller tiles and opacity culling only drop (tile, Gaussian) pairs that the reference's own
    # alpha < 1/255 rule skips at every pixel: the per-pixel sequence of composited Gaussians and
    # the arithmetic are unchanged, so the images are identical, not just close.
    for scene in (pixel_aligned_scene(20, 36, seed=1),
                  random_scene(300, 33, 47, seed=5, opacity_range=(0.01, 1.0))):
        s = scene.to(device=device)
        exact = rasterize(*s.args(), settings=RasterSettings.reference())
        out = rasterize(*s.args(), settings=settings)
        for a, b in zip((out.color, out.alpha, out.depth), (exact.color, exact.alpha,
                                                            exact.depth)):
            assert torch.equal(a, b)
        if settings.opacity_cull:
            assert out.aux["num_pairs"] > 0


# ---- Bad and degenerate input: never NaN, and the reference's answer ----

def _single(means, covs, opacities, shape=(16, 16), sh=None, near=0.5):
    g = means.shape[0]
    c2w = torch.eye(4)[None]
    if sh is None:
        sh = torch.rand(1, g, 3, 4, generator=torch.Generator().manual_seed(0)) - 0.5
    return GaussianScene(
        extrinsics=c2w, intrinsics=torch.tensor([[[0.9, 0, 0.5], [0, 0.9, 0.5], [0, 0, 1]]]),
        near=torch.tensor([near]), far=torch.tensor([100.0]), image_shape=shape,
        background_color=torch.tensor([[0.2, 0.3, 0.4]]), means=means[None],
        covariances=covs[None], sh_coefficients=sh, opacities=opacities[None])


def _case(name):
    eye = torch.eye(3)
    if name == "singular_covariances":  # rank 0, 1 and 2
        covs = torch.stack([torch.zeros(3, 3), torch.diag(torch.tensor([0.1, 0, 0])),
                            torch.diag(torch.tensor([0.05, 0.02, 0.0]))])
        return _single(torch.tensor([[0.0, 0, 2], [0.2, 0.1, 2.5], [-0.3, 0, 3]]), covs,
                       torch.tensor([0.8, 0.7, 0.9]))
    if name == "non_positive_definite":
        covs = torch.stack([torch.diag(torch.tensor([0.05, -0.04, 0.02])),
                            torch.diag(torch.tensor([-0.1, -0.1, -0.1])),
                            torch.tensor([[0.01, 0.2, 0], [0.2, 0.01, 0], [0, 0, 0.01]])])
        return _single(torch.tensor([[0.0, 0, 2], [0.2, 0.1, 2.5], [-0.3, 0, 3]]), covs,
                       torch.tensor([0.8, 0.7, 0.9]))
    if name == "behind_and_crossing_near_plane":
        means = torch.tensor([[0.0, 0, -1.0], [0.1, 0, 0.0], [0.0, 0.1, 0.09], [0.0, 0, 0.11],
                              [0.1, -0.1, 0.5]])
        covs = torch.stack([0.3 * eye, 0.3 * eye, 0.3 * eye, 0.01 * eye, 0.2 * eye])
        return _single(means, covs, torch.full((5,), 0.6))
    if name == "mean_at_camera_centre":
        return _single(torch.zeros(1, 3), 0.1 * eye[None], torch.tensor([0.9]))
    if name == "zero_and_tiny_opacity":
        means = torch.tensor([[0.0, 0, 2], [0.1, 0, 2], [0.0, 0.1, 2]])
        return _single(means, 0.01 * eye.expand(3, 3, 3), torch.tensor([0.0, 1 / 255, 0.003]))
    if name == "covers_whole_image":
        return _single(torch.tensor([[0.0, 0, 1.0], [0.5, 0.5, 3]]),
                       torch.stack([400 * eye, 0.01 * eye]), torch.tensor([0.5, 0.9]),
                       shape=(20, 24))
    if name == "extreme_anisotropy":
        g = torch.Generator().manual_seed(3)
        rot = random_rotations(8, g)
        scales = torch.tensor([3.0, 1e-4, 1e-4]).expand(8, 3)
        means = torch.cat([torch.rand(8, 2, generator=g) - 0.5, torch.full((8, 1), 3.0)], 1)
        return _single(means, covariances_from(rot, scales), torch.full((8,), 0.9),
                       shape=(24, 24))
    if name == "huge_and_tiny_values":
        means = torch.tensor([[0.0, 0, 1e6], [1e3, 1e3, 1.0], [0.0, 0, 2.0]])
        covs = torch.stack([1e10 * eye, 1e-12 * eye, 1e-3 * eye])
        return _single(means, covs, torch.tensor([0.9, 0.9, 0.9]))
    raise KeyError(name)


CASES = ["singular_covariances", "non_positive_definite", "behind_and_crossing_near_plane",
         "mean_at_camera_centre", "zero_and_tiny_opacity", "covers_whole_image",
         "extreme_anisotropy", "huge_and_tiny_values"]


@pytest.mark.parametrize("case", CASES)
def test_degenerate_input_is_finite_and_matches_reference(device, case):
    scene = _case(case)
    ours, ref = render_both(scene, device)
    # Needles (scales 3 : 1e-4) project to 2D covariances with condition number ~1.5e3, so the
    # float32 determinant (a c - b^2, cancelling) carries ~1.5e-4 relative error into the conic
    # and ~2e-5 into alpha; the reference CUDA code computes it the same way in float32.
    atol = 1e-4 if case == "extreme_anisotropy" else ATOL
    assert_matches(ours, ref, depth_scale=1e6 if case == "huge_and_tiny_values" else 10.0,
                   atol=atol)


@pytest.mark.parametrize("case", CASES)
def test_degenerate_input_gradients_are_finite(device, case):
    s = _case(case).to(device=device)
    leaves = [s.means, s.covariances, s.sh_coefficients, s.opacities]
    for t in leaves:
        t.requires_grad_(True)
    out = rasterize(*s.args())
    (out.color.sum() + out.alpha.sum() + out.depth.sum()).backward()
    for t in leaves:
        assert torch.isfinite(t.grad).all()


def test_no_gaussians(device):
    scene = _single(torch.zeros(0, 3), torch.zeros(0, 3, 3), torch.zeros(0),
                    sh=torch.zeros(1, 0, 3, 1)).to(device=device)
    scene.means.requires_grad_(True)
    out = rasterize(*scene.args())
    assert torch.equal(out.color, scene.background_color[:, :, None, None].expand(1, 3, 16, 16))
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    out.color.sum().backward()
    assert scene.means.grad.shape == (1, 0, 3)


def test_culled_gaussians_render_background(device):
    # Everything behind the camera: the background everywhere, exactly.
    scene = _single(torch.tensor([[0.0, 0, -2], [0.5, 0, -1]]), 0.1 * torch.eye(3).expand(2, 3, 3),
                    torch.tensor([0.9, 0.9])).to(device=device)
    out = rasterize(*scene.args())
    assert torch.equal(out.color, scene.background_color[:, :, None, None].expand(1, 3, 16, 16))
    assert out.aux["num_pairs"] == 0


def test_depth_is_weighted_camera_z(device):
    # One opaque-ish Gaussian facing the camera: depth = alpha x z at every pixel.
    scene = _single(torch.tensor([[0.0, 0, 2.5]]), 0.02 * torch.eye(3)[None], torch.tensor([0.7]))
    out = rasterize(*scene.to(device=device).args())
    torch.testing.assert_close(out.depth, out.alpha * 2.5, rtol=1e-6, atol=1e-7)


def test_scale_invariance(device):
    # render_cuda is scale-invariant: scaling the scene, cameras and near/far by s changes only
    # depth (by s). 1e-3 and 1e3 are the stability stress scales. Float32 rounding of the
    # scaled inputs changes results by ~1e-6.
    base = random_scene(150, 24, 24, seed=9)
    out = rasterize(*base.to(device=device).args())
    for s in (1e-3, 1e3):
        sc = base.to(device=device)
        sc.extrinsics = sc.extrinsics.clone()
        sc.extrinsics[:, :3, 3] *= s
        sc.means, sc.covariances = sc.means * s, sc.covariances * (s * s)
        sc.near, sc.far = sc.near * s, sc.far * s
        o = rasterize(*sc.args())
        torch.testing.assert_close(o.color, out.color, rtol=0, atol=2e-5)
        torch.testing.assert_close(o.depth, out.depth * s, rtol=1e-4, atol=2e-5 * s)


def test_wide_field_of_view(device):
    # fov near 180 degrees (fx = 0.02 W) and near 0 (fx = 50 W): finite, and the reference.
    for f in (0.02, 50.0):
        scene = random_scene(100, 16, 16, seed=int(f * 100))
        scene.intrinsics[:, 0, 0] = f
        scene.intrinsics[:, 1, 1] = f
        ours, ref = render_both(scene, device)
        assert_matches(ours, ref)
        assert math.isfinite(ours.color.sum().item())
