"""The decoder: Gaussians predicted per target view, rendered from the target cameras by the
Dr.Jit rasteriser (``usplat_dr.render.rasterize``), optionally pruned per target first
(``usplat_dr.render.prune``). The encoder side (``UniqueSplat.forward``) hands it a
``Gaussians`` batch of B N sets, target n of scene b at b N + n (pixelSplat's crossing:
encoder -> Gaussians -> decoder)."""

from dataclasses import dataclass

import torch
from jaxtyping import Float, Int
from torch import Tensor

from usplat_dr.model.types import Gaussians
from usplat_dr.render.prune import PruneSettings
from usplat_dr.render.prune import prune as prune_gaussians
from usplat_dr.render.settings import RasterSettings


@dataclass
class DecoderOutput:
    color: Float[Tensor, "b n 3 h w"]
    alpha: Float[Tensor, "b n h w"]  # 1 - final transmittance
    depth: Float[Tensor, "b n h w"]  # alpha-weighted camera-space z (not divided by alpha)
    rendered: Int[Tensor, "b n"]  # Gaussians rendered per target (after pruning)


class DecoderSplatting:
    """Renders a ``Gaussians`` batch for its target views. ``settings``: the rasteriser's
    (default: MVSplat's SH basis, which the model predicts in)."""

    def __init__(self, settings: RasterSettings | None = None):
        self.settings = settings or RasterSettings(sh_basis="mvsplat")

    def forward(self, gaussians: Gaussians, target_extrinsics: Float[Tensor, "b n 4 4"],
                target_intrinsics: Float[Tensor, "b n 3 3"], target_near: Float[Tensor, "b n"],
                target_far: Float[Tensor, "b n"], image_shape: tuple[int, int],
                background_color: Tensor | None = None,
                prune: PruneSettings | None = None) -> DecoderOutput:
        """Render target n of scene b from ``gaussians[b N + n]`` at ``image_shape`` (any size:
        the intrinsics are normalised), after pruning it for that view when ``prune`` is given
        (inference only)."""
        from usplat_dr.render import rasterize  # Dr.Jit on the first render (start-up time)

        b, n = target_near.shape
        g = gaussians
        bg = (torch.zeros(b * n, 3, device=g.means.device) if background_color is None
              else background_color.to(g.means).expand(b * n, 3))
        ext, intr = target_extrinsics.flatten(0, 1), target_intrinsics.flatten(0, 1)
        near = target_near.flatten()
        gauss = (g.means, g.covariances, g.harmonics, g.opacities)
        if prune is not None:
            if torch.is_grad_enabled() and g.means.requires_grad:
                raise ValueError("prune works at inference only: run under torch.no_grad() "
                                 "or pass prune=None")
            p = prune_gaussians(ext, intr, near, image_shape, *gauss, prune)
            gauss = (p.means, p.covariances, p.harmonics, p.opacities)
            rendered = p.counts.view(b, n)
        else:
            rendered = torch.full((b, n), len(g), device=g.means.device)
        r = rasterize(ext, intr, near, target_far.flatten(), image_shape, bg, *gauss,
                      self.settings)
        return DecoderOutput(color=r.color.unflatten(0, (b, n)),
                             alpha=r.alpha.unflatten(0, (b, n)),
                             depth=r.depth.unflatten(0, (b, n)), rendered=rendered)

    __call__ = forward
