"""Gradients of the rasteriser against torch autograd of the float64 reference, and against
central finite differences.

Tolerances: the float32 backward recovers T by division and sums over ~50 splats per pixel;
observed relative errors are 3e-7 .. 2e-6 (relative L2 and max error / max |g|). 1e-4 leaves a
50x margin; a wrong rule (gradient through an active clamp, a missing skip, a sign) gives errors
of 1e-2 or more.
"""

import pytest
import torch

from tests.render.helpers import gradients, weighted_loss, with_grad
from usplat_dr.geometry.cameras import normalized_intrinsics
from usplat_dr.render import RasterSettings, rasterize
from usplat_dr.render.reference import render_ref
from usplat_dr.render.scenes import (
    GaussianScene,
    covariances_from,
    pixel_aligned_scene,
    random_rotations,
    random_scene,
    sh_from_rgb,
)

NAMES = ("means", "covariances", "sh_coefficients", "opacities")
RTOL = 1e-4


def assert_grads_close(ours, ref):
    for name, a, b in zip(NAMES, ours, ref):
        assert torch.isfinite(a).all(), name
        scale = b.abs().max().item()
        assert scale > 0, f"{name}: the reference gradient is all zero (test scene too weak)"
        rel_l2 = ((a - b).norm() / b.norm()).item()
        rel_max = ((a - b).abs().max() / scale).item()
        assert rel_l2 <= RTOL and rel_max <= RTOL, (name, rel_l2, rel_max)


SCENES = {
    "random_batch2": lambda: random_scene(300, 32, 32, batch=2, seed=1),
    "pixel_aligned": lambda: pixel_aligned_scene(16, 24, seed=3),
    "high_opacity_clamp_and_stop": lambda: random_scene(200, 24, 40, seed=2,
                                                        opacity_range=(0.9, 1.0),
                                                        scale_range=(0.1, 0.5)),
    "not_multiple_of_16": lambda: random_scene(200, 24, 40, seed=6, sh_degree=3),
}


@pytest.mark.parametrize("scene", SCENES)
def test_gradients_match_reference_autograd(device, scene):
    sc = SCENES[scene]()
    ours = gradients(sc, rasterize, torch.float32, device)
    ref = gradients(sc, render_ref, torch.float64)
    assert_grads_close(ours, ref)


TILINGS = [RasterSettings(tile_size=t, opacity_cull=c, backward_scatter=m)
           for t in (4, 8, 16) for c in (True, False) for m in ("packet", "lanes")]


@pytest.mark.parametrize("settings", TILINGS,
                         ids=[f"tile{s.tile_size}-cull{int(s.opacity_cull)}-{s.backward_scatter}"
                              for s in TILINGS])
@pytest.mark.parametrize("scene", ["random_batch2", "high_opacity_clamp_and_stop"])
def test_gradients_at_every_tiling(device, scene, settings):
    # 16 is the CUDA default and the reference's own cut; 4 and 8 are the CPU choices. Every
    # tiling must differentiate the same function, clamp and early stop included, so its
    # backward is proven here before a GPU runs it; with both ways of adding the gradients
    # (the packet record with Expand, LLVM's default; the ten scalar scatters, CUDA's).
    sc = SCENES[scene]()
    ours = gradients(sc, rasterize, torch.float32, device, settings=settings)
    assert_grads_close(ours, gradients(sc, render_ref, torch.float64))


def test_reference_clamp_gradient_mode(device):
    sc = SCENES["high_opacity_clamp_and_stop"]()
    settings = RasterSettings(clamp_gradient="reference")
    ours = gradients(sc, rasterize, torch.float32, device, settings=settings)
    ref = gradients(sc, render_ref, torch.float64, clamp_gradient="reference")
    assert_grads_close(ours, ref)
    exact = gradients(sc, rasterize, torch.float32, device)
    # The clamp is active in this scene, so the two gradient rules really differ.
    assert (exact[3] - ours[3]).abs().max() > 1e-3


def test_mvsplat_basis_gradients_and_ignored_degree_4(device):
    sc = random_scene(150, 24, 24, seed=8, sh_degree=4)
    settings = RasterSettings(sh_basis="mvsplat")
    ours = gradients(sc, rasterize, torch.float32, device, settings=settings)
    ref = gradients(sc, render_ref, torch.float64, basis="mvsplat")
    assert_grads_close(ours, ref)
    assert (ours[2][..., 16:] == 0).all()  # degree 4 is read but ignored, as the reference


def test_only_the_upper_triangle_of_covariances_is_read(device):
    grad = gradients(random_scene(100, 16, 16, seed=3), rasterize, torch.float32, device)[1]
    lower = torch.tril(torch.ones(3, 3, dtype=torch.bool), -1)
    assert (grad[..., lower] == 0).all()
    assert (grad[..., ~lower] != 0).any()


def _smooth_scene(n: int, seed: int) -> GaussianScene:
    """1-3 large Gaussians in one 16x16 tile where the render is smooth near the inputs.

    The render has jumps: a pixel where alpha crosses 1/255 changes by ~0.004, a depth-order
    swap or a T < 1e-4 stop changes it by O(1); the analytic gradient (rightly) ignores them but
    finite differences see them. Here projected sigmas are ~8 px, so the 1/255 contour (> 3
    sigma) lies outside the image; depths 3, 4, 5 never swap; alpha <= 0.6 never stops a pixel.
    """
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([0.3 * (torch.rand(n, 2, generator=g) - 0.5),
                       torch.tensor([3.0, 4.0, 5.0])[:n, None]], 1)
    rot = random_rotations(n, g)
    scales = torch.empty(n, 3).uniform_(1.6, 2.4, generator=g) * means[:, 2:] / 4.0
    sh = sh_from_rgb(torch.rand(n, 3, generator=g), 2, g, view_dependence=0.3)
    return GaussianScene(
        extrinsics=torch.eye(4)[None], intrinsics=normalized_intrinsics(0.9, 0.9, batch=(1,)),
        near=torch.tensor([0.5]), far=torch.tensor([50.0]), image_shape=(16, 16),
        background_color=torch.rand(1, 3, generator=g), means=means[None],
        covariances=covariances_from(rot, scales)[None], sh_coefficients=sh[None],
        opacities=torch.empty(1, n).uniform_(0.3, 0.6, generator=g))


@pytest.mark.parametrize("n", [1, 2, 3])
def test_gradients_match_finite_differences(device, n):
    # Directional central differences of the float32 renderer, h = 1e-2 (inputs of size ~1 ..
    # 5; the render is smooth here, so the O(h^2) truncation error is ~1e-4 relative). float32
    # rounding of the loss (~1e-6 relative of ~10) over 2h adds ~1e-3 absolute; derivatives are
    # ~1 .. 100, so 1e-2 relative (floor 1e-2 absolute) is ample, while a wrong derivative rule
    # is off by O(1).
    g = torch.Generator().manual_seed(100 + n)
    s = with_grad(_smooth_scene(n, seed=n), torch.float32, device)
    leaves = [s.means, s.covariances, s.sh_coefficients, s.opacities]
    out = rasterize(*s.args())
    # Every pixel lies within 12 px of every centre (half-diagonal 11.3 px + offsets < 1 px) and
    # inside every 3-sigma radius, so no pixel sits near a 1/255 contour or the tile cut.
    assert out.aux["radii"].min() > 12
    weighted_loss(out.color, out.alpha, out.depth).backward()
    h = 1e-2
    for name, leaf in zip(NAMES, leaves):
        direction = torch.randn(leaf.shape, generator=g).to(device)
        if name == "covariances":  # keep them symmetric positive definite
            direction = 0.1 * (direction + direction.transpose(-1, -2))
        analytic = (leaf.grad * direction).sum().item()

        def loss_at(step, leaf=leaf, direction=direction):  # B023: this iteration's values
            with torch.no_grad():
                saved = leaf.clone()
                leaf.add_(step * direction)
                o = rasterize(*s.args())
                leaf.copy_(saved)
                return weighted_loss(o.color, o.alpha, o.depth).double().item()

        numeric = (loss_at(h) - loss_at(-h)) / (2 * h)
        assert abs(numeric - analytic) <= 1e-2 * max(abs(analytic), 1.0), (name, numeric,
                                                                          analytic)
