"""Context images and cameras in, novel views out: what ``UniqueSplat.predict`` does, for users
with their own images (no dataset, no batch dicts).

Conventions, as everywhere in usplat-dr (the field's): intrinsics normalised by the image size
(fx/W, fy/H, cx/W, cy/H), extrinsics camera-to-world in OpenCV axes (+X right, +Y down, +Z
forward), images in [0, 1] (float) or 0-255 (uint8), channels first or last. Cameras are
keyword arguments: each is easy to pass in the wrong place and the shapes [3, 3] and [4, 4]
are the only other check.
"""

import logging
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from usplat_dr.geometry.cameras import Cameras
from usplat_dr.model.auto_budget import AutoBudget, make_budget
from usplat_dr.model.types import Gaussians

log = logging.getLogger(__name__)

#: near/far of the field's released checkpoints (MVSplat's RE10K and ACID: 1 and 100, in the
#: datasets' units); synthetic scenes of ``usplat synth`` use 0.2 and 20 and record theirs.
DEFAULT_NEAR, DEFAULT_FAR = 1.0, 100.0
#: A normalised principal point lies in [0, 1]; one beyond this is in pixels.
MAX_NORMALISED = 4.0


@dataclass
class Prediction:
    """What ``predict`` returns for N target cameras: ``gaussians[n]`` the Gaussians predicted
    for target n (each target has its own set in (c)); ``color`` [N, 3, H, W] in [0, 1];
    ``alpha`` [N, H, W] (accumulated opacity); ``depth`` [N, H, W] the expected distance along
    each pixel's ray divided by alpha (alpha clamped at 1e-3: pixels nothing covers read ~0).
    ``auto_keep``: the fraction of the Gaussians the automatic count chose (``budget="auto"``),
    else ``None``."""

    gaussians: list[Gaussians]
    color: Tensor
    alpha: Tensor
    depth: Tensor
    auto_keep: float | None = None


def _tensor(name: str, value, dims: int, tail: tuple[int, ...]) -> Tensor:
    """``value`` as a float32 tensor of ``dims`` dimensions ending in ``tail``; one fewer
    dimension (a single camera) gets a leading 1."""
    t = torch.as_tensor(np.asarray(value) if not isinstance(value, Tensor) else value)
    if t.ndim == dims - 1:
        t = t[None]
    if t.ndim != dims or tuple(t.shape[1:]) != tail:
        raise ValueError(f"{name} must have shape [N, {', '.join(map(str, tail))}], got "
                         f"{list(t.shape)}")
    t = t.float()
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} holds non-finite values")
    return t


def _images(images) -> Tensor:
    """[V, 3, H, W] float in [0, 1] from a list or array of images: uint8 0-255 or float
    0-1, channels last ([V, H, W, 3], as image files load) or first."""
    if isinstance(images, (list, tuple)):
        images = [torch.as_tensor(np.asarray(im)) if not isinstance(im, Tensor) else im
                  for im in images]
        shapes = {tuple(im.shape) for im in images}
        if len(shapes) != 1:
            raise ValueError(f"images must all have the same shape, got {sorted(shapes)}")
        t = torch.stack(images)
    else:
        t = torch.as_tensor(np.asarray(images)) if not isinstance(images, Tensor) else images
    if t.ndim != 4 or 3 not in (t.shape[1], t.shape[-1]):
        raise ValueError(f"images must be V images [V, H, W, 3] or [V, 3, H, W], got shape "
                         f"{list(t.shape)}")
    if t.shape[1] != 3:
        t = t.permute(0, 3, 1, 2)
    if t.dtype == torch.uint8:
        return t.float() / 255.0
    t = t.float()
    if not torch.isfinite(t).all() or t.min() < 0 or t.max() > 1:
        raise ValueError("images must be uint8 (0-255) or float in [0, 1]")
    return t


def _bounds(name: str, value, views: int) -> Tensor:
    """near or far per view from a number or a list of ``views`` numbers."""
    if value is None:  # UserViews.near/far of a camera file without sparse points
        raise ValueError(f"{name}= is None: pass the depth range in scene units (near=, far=). "
                         "A camera file without sparse points (a transforms.json) sets none; "
                         "estimate one from two views with usplat_dr.geometry.plane_sweep."
                         "near_far_from_sweep, or read it off usplat render's printed line")
    t = torch.as_tensor(value, dtype=torch.float32).reshape(-1)
    if t.numel() == 1:
        t = t.expand(views)
    if t.numel() != views or not torch.isfinite(t).all() or (t <= 0).any():
        raise ValueError(f"{name} must be a positive number or one per context view "
                         f"({views}), got {value!r}")
    return t.clone()


def _check_normalised(name: str, k: Tensor) -> None:
    if (k[:, :2, 2].abs() > MAX_NORMALISED).any() or (k[:, 2] != torch.tensor(
            [0.0, 0.0, 1.0])).any():
        raise ValueError(f"{name} must be normalised intrinsics [[fx/W, 0, cx/W], [0, fy/H, "
                         f"cy/H], [0, 0, 1]]; these look like pixels: divide row 0 by the "
                         f"image width and row 1 by its height")


@torch.no_grad()
def predict_views(model, images, *, intrinsics, extrinsics, target_intrinsics,
                  target_extrinsics, near=DEFAULT_NEAR, far=DEFAULT_FAR,
                  chunk: int = 8, budget=None, rank_by: str | None = None,
                  all_gaussians: bool = True, tolerance: float | None = None) -> Prediction:
    """Predict and render ``target_*`` cameras from the context ``images`` with ``model`` (a
    ``UniqueSplat``), in its evaluation mode, ``chunk`` targets per forward pass, keeping
    ``budget`` Gaussians per target ranked by ``rank_by`` (``None``: all; ``"auto"``: the
    automatic count within ``tolerance`` dB, chosen once for the scene). See
    ``UniqueSplat.predict``. ``all_gaussians=False``: ``gaussians`` holds the first target's
    set only, so that a long camera path holds the Gaussians of ``chunk`` targets at a time."""
    if not isinstance(chunk, int) or chunk < 1:
        raise ValueError(f"chunk must be an int >= 1, got {chunk!r}")
    device = next(model.parameters()).device
    imgs = _images(images)
    v = imgs.shape[0]
    k = _tensor("intrinsics", intrinsics, 3, (3, 3))
    e = _tensor("extrinsics", extrinsics, 3, (4, 4))
    tk = _tensor("target_intrinsics", target_intrinsics, 3, (3, 3))
    te = _tensor("target_extrinsics", target_extrinsics, 3, (4, 4))
    for name, t, n in (("intrinsics", k, v), ("extrinsics", e, v),
                       ("target_intrinsics", tk, tk.shape[0])):
        if t.shape[0] != n:
            raise ValueError(f"{name} must hold one camera per image ({n}), got {t.shape[0]}")
    if te.shape[0] != tk.shape[0]:
        raise ValueError(f"target_extrinsics and target_intrinsics must hold as many cameras, "
                         f"got {te.shape[0]} and {tk.shape[0]}")
    _check_normalised("intrinsics", k)
    _check_normalised("target_intrinsics", tk)
    near_t, far_t = _bounds("near", near, v), _bounds("far", far, v)
    if (far_t <= near_t).any():
        raise ValueError(f"far must exceed near, got near {near!r}, far {far!r}")
    was_training = model.training
    model.eval()
    gaussians, colors, alphas, depths = [], [], [], []
    try:
        images = imgs[None].to(device)
        context = Cameras(e[None].to(device), k[None].to(device), near_t[None].to(device),
                          far_t[None].to(device))
        keep = make_budget(budget, rank_by, tolerance)
        prune, auto_keep = "auto", None
        for s in range(0, tk.shape[0], chunk):
            n = min(chunk, tk.shape[0] - s)
            targets = Cameras(te[None, s:s + n].to(device), tk[None, s:s + n].to(device),
                              near_t.min().expand(1, n).to(device),
                              far_t.max().expand(1, n).to(device))
            out = model(images, context, targets, budget=keep, prune=prune)
            if isinstance(keep, AutoBudget):  # chosen once: the later chunks reuse it
                auto_keep = float(out.aux["auto_keep"][0])
                keep, prune = out.aux["auto_budget"], out.aux["auto_prune"]
                log.info("the automatic count keeps %.0f%% of the Gaussians (%d of %d per "
                         "target), %.0f rendered after merging near-duplicates", 100 * auto_keep,
                         int(out.aux["kept"][0, 0]), int(out.aux["auto_total"]),
                         float(out.aux["rendered"][0].float().mean()))
            if all_gaussians or not gaussians:
                gaussians += [out.target(0, i) for i in range(n if all_gaussians else 1)]
            colors.append(out.color[0].clamp(0, 1))
            alphas.append(out.alpha[0])
            depths.append(out.depth[0] / out.alpha[0].clamp(min=1e-3))
    finally:
        model.train(was_training)
    return Prediction(gaussians, torch.cat(colors), torch.cat(alphas), torch.cat(depths),
                      auto_keep)
