"""Per-scene Gaussian optimisation with our rasteriser (a renderer check on known geometry):
initialise Gaussians from a scene's depth maps, optimise means, scales, rotations, opacities
and SH on the training views, measure PSNR/SSIM on held-out views. ``usplat fit``
(``usplat_dr.jobs.fit``) runs it on a synthetic scene; ``train/examples/`` use its parts.

Follows 3D Gaussian Splatting (Kerbl et al. 2023, sec. 5-6): per-parameter Adam learning
rates, loss 0.8 L1 + 0.2 (1 - SSIM), scales as logs, opacities as logits, quaternions
normalised in the covariance. No densification: the depth initialisation already places one
Gaussian per pixel of the initial views, which is what the scene needs at this resolution.
"""

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor
from tqdm import tqdm

from usplat_dr.data.chunks import cameras_to_matrices, decode_image
from usplat_dr.evaluation.metrics import psnr, ssim, ssim_torch
from usplat_dr.geometry.cameras import pixel_directions
from usplat_dr.geometry.quaternions import quat_xyzw_to_matrix
from usplat_dr.io.images import save_png
from usplat_dr.render import rasterize
from usplat_dr.render.scenes import covariances_from
from usplat_dr.render.sh import C0


@dataclass(frozen=True)
class FitCfg:
    """The optimisation's settings (3DGS's learning rates, no densification)."""

    iterations: int = 1500
    batch_views: int = 2  # training views rendered per step
    sh_degree: int = 1
    init_stride: int = 1  # unproject every n-th pixel of the initial views
    init_every: int = 2  # use every n-th training view for the initialisation
    lr_means: float = 2e-4  # x scene extent (mean initial depth)
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacities: float = 5e-2
    lr_sh_dc: float = 5e-3
    lr_sh_rest: float = 2.5e-4
    ssim_weight: float = 0.2
    seed: int = 0


@dataclass
class FitResult:
    """What ``fit`` measured on the held-out views, before and after the optimisation."""

    psnr_before: float  # held-out, at initialisation
    psnr_after: float
    ssim_before: float
    ssim_after: float
    seconds: float
    num_gaussians: int
    history: list[tuple[int, float]] = field(default_factory=list)  # (step, held-out PSNR)


@dataclass
class SceneViews:
    """Everything a fit needs from a scene: images [V, 3, H, W] in [0, 1], c2w [V, 4, 4],
    normalised intrinsics [V, 3, 3], camera-space depth [V, H, W] (+inf on a miss)."""

    images: Float[Tensor, "view 3 h w"]
    extrinsics: Float[Tensor, "view 4 4"]
    intrinsics: Float[Tensor, "view 3 3"]
    depths: Float[Tensor, "view h w"]
    near: float
    far: float
    background: Float[Tensor, " 3"]


def views_from_record(scene: dict) -> SceneViews:
    """A synthetic chunk record (``usplat synth``) as ``SceneViews``."""
    c2w, k = cameras_to_matrices(scene["cameras"])
    images = torch.stack([decode_image(im) for im in scene["images"]]).float() / 255.0
    depths = scene["depths"].float()
    miss = ~torch.isfinite(depths)
    # Background: the mean colour of missed pixels (the sky), black when every ray hits.
    bg = images.permute(0, 2, 3, 1)[miss].mean(0) if miss.any() else torch.zeros(3)
    near, far = (float(x) for x in scene["near_far"])
    return SceneViews(images, c2w, k, depths, near, far, bg)


def split_views(num_views: int, hold_every: int = 4) -> tuple[list[int], list[int]]:
    """Held-out views: every ``hold_every``-th frame starting at 2 (interpolated, never the
    first or last frame); the rest train."""
    held = list(range(2, num_views - 1, hold_every))
    return [i for i in range(num_views) if i not in held], held


def init_from_depth(views: SceneViews, which: list[int], stride: int, sh_degree: int):
    """One Gaussian per (strided) pixel of the given views, at the depth Mitsuba traced,
    coloured by the pixel, sized to the pixel footprint, half opaque."""
    means, colors, scales = [], [], []
    h, w = views.depths.shape[1:]
    for v in which:
        d = views.depths[v, ::stride, ::stride]
        k = views.intrinsics[v]
        ok = torch.isfinite(d)
        dirs = torch.from_numpy(pixel_directions(k.numpy(), (h, w))[::stride, ::stride]).float()
        cam = torch.cat([dirs * d[..., None], torch.ones_like(d)[..., None]], -1)[ok]  # [N, 4]
        means.append((cam @ views.extrinsics[v].T)[:, :3])
        colors.append(views.images[v, :, ::stride, ::stride].permute(1, 2, 0)[ok])
        footprint = d[ok] / (k[0, 0] * w) * stride  # pixel size at that depth
        scales.append(footprint[:, None].expand(-1, 3) * 0.7)
    means, colors, scales = torch.cat(means), torch.cat(colors), torch.cat(scales)
    n = len(means)
    sh = torch.zeros(n, 3, (sh_degree + 1) ** 2)
    sh[..., 0] = (colors - 0.5) / C0
    return {
        "means": means,
        "log_scales": scales.clamp_min(1e-6).log(),
        "quats_xyzw": torch.tensor([0.0, 0.0, 0.0, 1.0]).repeat(n, 1),
        "opacity_logits": torch.full((n,), math.log(0.7 / 0.3)),
        "sh_dc": sh[..., :1].contiguous(),
        "sh_rest": sh[..., 1:].contiguous(),
    }


def render_views(params: dict, views: SceneViews, which: list[int]):
    """Render the Gaussians ``params`` (as ``init_from_depth`` makes them) from the views
    ``which`` of ``views``: a ``usplat_dr.render.RenderOutput`` with a batch of ``len(which)``."""
    b = len(which)
    cov = covariances_from(quat_xyzw_to_matrix(params["quats_xyzw"]), params["log_scales"].exp())
    sh = torch.cat([params["sh_dc"], params["sh_rest"]], -1)
    g = len(params["means"])
    idx = torch.tensor(which)
    return rasterize(views.extrinsics[idx], views.intrinsics[idx],
                     torch.full((b,), views.near), torch.full((b,), views.far),
                     tuple(views.images.shape[-2:]), views.background.expand(b, 3),
                     params["means"].expand(b, g, 3), cov.expand(b, g, 3, 3),
                     sh.expand(b, *sh.shape), torch.sigmoid(params["opacity_logits"]).expand(b, g))


def evaluate_views(params: dict, views: SceneViews, which: list[int]
                   ) -> tuple[float, float, Tensor]:
    """Mean PSNR and SSIM (the field's protocol) of the views ``which`` rendered from
    ``params``, and the renders [len(which), 3, H, W]; no gradients."""
    with torch.no_grad():
        out = render_views(params, views, which)
    gt = views.images[which]
    return psnr(out.color, gt).mean().item(), ssim(out.color, gt).mean().item(), out.color


def fit(views: SceneViews, cfg: FitCfg = FitCfg(), out_png: str | Path | None = None,
        progress: bool = True) -> FitResult:
    """Optimise Gaussians on the training views of ``views``; evaluate on the held-out ones.

    Writes ``out_png`` (held-out views: ground truth, initial render, final render, error) when
    given."""
    if cfg.iterations < 1 or cfg.batch_views < 1:
        raise ValueError("iterations and batch_views must be >= 1")
    torch.manual_seed(cfg.seed)
    train, held = split_views(len(views.images))
    params = init_from_depth(views, train[::cfg.init_every], cfg.init_stride, cfg.sh_degree)
    extent = float(params["means"].sub(params["means"].mean(0)).norm(dim=-1).mean())
    for p in params.values():
        p.requires_grad_(True)
    opt = torch.optim.Adam([
        {"params": [params["means"]], "lr": cfg.lr_means * extent},
        {"params": [params["log_scales"]], "lr": cfg.lr_scales},
        {"params": [params["quats_xyzw"]], "lr": cfg.lr_quats},
        {"params": [params["opacity_logits"]], "lr": cfg.lr_opacities},
        {"params": [params["sh_dc"]], "lr": cfg.lr_sh_dc},
        {"params": [params["sh_rest"]], "lr": cfg.lr_sh_rest},
    ], eps=1e-15)
    # Means: exponential decay to 1/100 over the run (3DGS's position schedule).
    decay = 0.01 ** (1 / cfg.iterations)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, [lambda s: decay**s] + [lambda s: 1.0] * 5)

    psnr0, ssim0, render0 = evaluate_views(params, views, held)
    history = [(0, psnr0)]
    gen = torch.Generator().manual_seed(cfg.seed)
    t0 = time.perf_counter()
    bar = None
    if progress:
        bar = tqdm(total=cfg.iterations, desc="fit", unit="step")
    for step in range(1, cfg.iterations + 1):
        pick = torch.randperm(len(train), generator=gen)[:cfg.batch_views].tolist()
        which = [train[i] for i in pick]
        out = render_views(params, views, which)
        gt = views.images[which]
        loss = ((1 - cfg.ssim_weight) * (out.color - gt).abs().mean()
                + cfg.ssim_weight * (1 - ssim_torch(out.color, gt).mean()))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if bar is not None:
            bar.update(1)
            if step % 50 == 0:
                bar.set_postfix(loss=f"{loss.item():.4f}")
        if step % max(cfg.iterations // 5, 1) == 0 or step == cfg.iterations:
            history.append((step, evaluate_views(params, views, held)[0]))
    if bar is not None:
        bar.close()
    seconds = time.perf_counter() - t0
    psnr1, ssim1, render1 = evaluate_views(params, views, held)
    if out_png is not None:
        _save_comparison(Path(out_png), views.images[held], render0, render1)
    return FitResult(psnr0, psnr1, ssim0, ssim1, seconds, len(params["means"]), history)


def _save_comparison(path: Path, gt: Tensor, before: Tensor, after: Tensor) -> None:
    rows = []
    for g, b, a in zip(gt, before, after):
        err = (a - g).abs().mean(0, keepdim=True).expand(3, -1, -1) * 4  # error x4
        rows.append(torch.cat([g, b.clamp(0, 1), a.clamp(0, 1), err.clamp(0, 1)], -1))
    save_png(path, torch.cat(rows, -2).permute(1, 2, 0).numpy().astype(np.float64))
