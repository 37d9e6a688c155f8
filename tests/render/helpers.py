"""Helpers shared by the rasteriser tests."""

import torch

from usplat_dr.render import rasterize
from usplat_dr.render.reference import render_ref
from usplat_dr.render.scenes import GaussianScene


def render_both(scene: GaussianScene, device, settings=None, basis="3dgs", **ref_kwargs):
    """(ours on ``device`` in float32, dense float64 reference on the CPU) for one scene."""
    ours = rasterize(*scene.to(device=device).args(), settings=settings)
    ref = render_ref(*scene.to(dtype=torch.float64).args(), basis=basis, **ref_kwargs)
    return ours, ref


def max_err(ours, ref):
    """Max abs error of (color, alpha, depth)."""
    return [(a.detach().double().cpu() - b).abs().max().item()
            for a, b in zip((ours.color, ours.alpha, ours.depth), ref)]


def with_grad(scene: GaussianScene, dtype, device="cpu") -> GaussianScene:
    """A copy of ``scene`` whose four Gaussian tensors are fresh leaves requiring grad."""
    s = scene.to(device=device, dtype=dtype)
    for name in ("means", "covariances", "sh_coefficients", "opacities"):
        setattr(s, name, getattr(s, name).clone().requires_grad_(True))
    return s


def weighted_loss(color, alpha, depth, seed=5):
    """A loss that weights every output pixel differently (random, seeded, float64 weights)."""
    g = torch.Generator().manual_seed(seed)
    total = 0
    for t in (color, alpha, depth):
        w = torch.randn(t.shape, generator=g, dtype=torch.float64).to(t.device, t.dtype)
        total = total + (t * w).sum()
    return total


def gradients(scene: GaussianScene, fn, dtype, device="cpu", **kwargs):
    """Gradients of ``weighted_loss`` w.r.t. means, covariances, SH and opacities."""
    s = with_grad(scene, dtype, device)
    out = fn(*s.args(), **kwargs)
    if hasattr(out, "color"):
        out = (out.color, out.alpha, out.depth)
    weighted_loss(*out).backward()
    return [t.grad.detach().double().cpu()
            for t in (s.means, s.covariances, s.sh_coefficients, s.opacities)]
