"""The training loss: MSE on the rendered target views, + LPIPS after ``loss.lpips_after_step``
(the field's recipe: MVSplat / pixelSplat), + optional log-depth supervision of the context
views' predicted depth and of the rendered targets' depth (docs/learning.md), + optionally, in
a step with a Gaussian budget, MSE of the unbudgeted render (``loss.full_render``).
``training_loss`` combines the terms as ``LossCfg`` weighs them; ``Trainer.loss`` calls it.
"""

import torch
from jaxtyping import Float
from torch import Tensor

from usplat_dr.data.types import model_inputs
from usplat_dr.evaluation.lpips import LPIPS
from usplat_dr.evaluation.protocol import depth_scored_pixels
from usplat_dr.geometry.cameras import pixel_centres
from usplat_dr.model.decoder import DecoderSplatting
from usplat_dr.model.uniquesplat import UniqueSplatOutput
from usplat_dr.training.config import LossCfg


def mse_loss(pred: Float[Tensor, "*batch 3 h w"],
             target: Float[Tensor, "*batch 3 h w"]) -> Float[Tensor, ""]:
    """Mean squared error over every pixel and channel (the field's photometric term)."""
    return (pred - target).square().mean()


def lpips_loss(lpips: LPIPS, pred: Float[Tensor, "b n 3 h w"],
               target: Float[Tensor, "b n 3 h w"]) -> Float[Tensor, ""]:
    """LPIPS (VGG) averaged over the target views, each view an image pair."""
    return lpips(pred.flatten(0, 1), target.flatten(0, 1)).mean()  # [B*N, 3, H, W]


def depth_loss(aux: dict, depth: Float[Tensor, "b v h w"],
               intrinsics: Float[Tensor, "b v 3 3"]) -> Float[Tensor, ""]:
    """Depth supervision of the context views: mean |log d_pred - log d_true| over the pixels
    with a finite positive ground-truth depth, on the refined and on the coarse depth
    (``aux``'s ``context_depths`` / ``context_coarse_depths``).

    ``depth`` [B, V, H, W] is camera-space z (synthetic sets carry it, +inf on a miss), while
    MVSplat's depth is the distance along the pixel's unit ray (the adapter places a Gaussian
    at origin + d * direction / |direction|), so z is converted: d = z |K^-1 (x, y, 1)| at
    the pixel centre (up to 15% apart at the corners of a 60-degree view). The log error is
    scale-free (for small errors it is AbsRel), so near and far scenes weigh alike; the coarse
    term keeps a gradient where the refined depth is clamped to [near, far] (the clamp
    passes none)."""
    b, v, h, w = depth.shape
    xy1 = torch.cat([pixel_centres(h, w, depth.device), depth.new_ones(h * w, 1)], -1)
    ray = torch.einsum("bvij,rj->bvri", intrinsics.inverse(), xy1).norm(dim=-1)  # [B, V, H*W]
    valid = torch.isfinite(depth) & (depth > 0)
    if not valid.any():
        return depth.new_zeros(())
    log_true = (depth * ray.view(b, v, h, w))[valid].log()
    total = depth.new_zeros(())
    for key in ("context_depths", "context_coarse_depths"):
        total = total + (aux[key][valid].log() - log_true).abs().mean()
    return total


def target_depth_loss(depth: Float[Tensor, "b n h w"], alpha: Float[Tensor, "b n h w"],
                      true_z: Float[Tensor, "b n h w"]) -> Float[Tensor, ""]:
    """Depth supervision of the rendered target views: mean |log(depth / alpha) - log z| over
    the pixels with a finite positive ground-truth z that the rendering covers (alpha > 0.5,
    the pixels the evaluation's AbsRel scores; ``evaluation.protocol.depth_metrics``).

    ``depth`` and ``alpha`` [B, N, H, W] are the rasteriser's alpha-weighted camera-space z and
    its opacity (gradients reach the Gaussians through both); ``true_z`` [B, N, H, W] the
    synthetic ground truth (+inf on a miss). Zero when no pixel qualifies."""
    valid = depth_scored_pixels(alpha.detach(), true_z)
    if not valid.any():
        return depth.new_zeros(())
    # alpha > 0.5 on valid pixels; the clamp keeps log finite where a depth is exactly 0
    pred = (depth[valid] / alpha[valid]).clamp(min=1e-6)
    return (pred.log() - true_z[valid].log()).abs().mean()


def training_loss(out: UniqueSplatOutput, batch: dict, cfg: LossCfg, step: int, device,
                  lpips: LPIPS | None = None) -> tuple[Tensor, dict]:
    """The loss of step ``step`` and its terms (for metrics.csv): ``cfg.mse`` x MSE on the
    targets, + ``cfg.depth`` x ``depth_loss`` and ``cfg.target_depth`` x ``target_depth_loss``
    where the data has depth (until ``cfg.depth_until_step``), + ``cfg.lpips`` x LPIPS from
    ``cfg.lpips_after_step`` on (``lpips``: the network, ``None`` when the run never uses
    it), + ``cfg.full_render`` x MSE of the unbudgeted render in a step with a Gaussian budget
    (``out.aux["unbudgeted"]``). ``batch``'s tensors are moved to ``device``."""
    pred = out.color
    target = batch["target"]["image"].to(device)
    mse = mse_loss(pred, target)
    loss = cfg.mse * mse
    parts = {"mse": mse.item()}
    depth_on = cfg.depth_until_step is None or step < cfg.depth_until_step
    if cfg.depth > 0 and depth_on and "depth" in batch["context"]:
        d = depth_loss(out.aux, batch["context"]["depth"].to(device),
                       batch["context"]["intrinsics"].to(device))
        loss = loss + cfg.depth * d
        parts["depth"] = d.item()
    if cfg.target_depth > 0 and depth_on and "depth" in batch["target"]:
        d = target_depth_loss(out.depth, out.alpha, batch["target"]["depth"].to(device))
        loss = loss + cfg.target_depth * d
        parts["target_depth"] = d.item()
    if cfg.full_render > 0 and "unbudgeted" in out.aux:
        # the unbudgeted Gaussians rendered as the model renders them (its default settings
        # and black background), so that a budgeted step also keeps the full model's quality
        t = model_inputs(batch, device)
        full = DecoderSplatting().forward(out.aux["unbudgeted"], t.target_extrinsics,
                                          t.target_intrinsics, t.target_near, t.target_far,
                                          tuple(target.shape[-2:]))
        m = mse_loss(full.color, target)
        loss = loss + cfg.full_render * m
        parts["full_mse"] = m.item()
    if lpips is not None and step >= cfg.lpips_after_step:
        lp = lpips_loss(lpips, pred, target)
        loss = loss + cfg.lpips * lp
        parts["lpips"] = lp.item()
    return loss, parts
