"""Where a Gaussian budget goes (docs/model.md, "A Gaussian budget chosen at inference").

The Gaussians are pixel-aligned: each is a pixel of a context view, so what a budget keeps is a
map over the context images (``out.aux["kept_mask"]``, averaged over the targets: each target
keeps its own K). The synthetic scenes know each pixel's material and depth, so the kept
fraction splits into textured against plain (textureless) surfaces and near against far
(below and above the median of the scene's context depths); ``usplat eval --gaussians K``
writes these per scene and per scene kind (``indoor``, ``outdoor``, ``object``: the prefix of
the scene's name), and images: each context view, its kept fraction, its material and depth.
"""

import math
import os
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Bool, Float
from torch import Tensor

from usplat_dr.data.synth.render import CONDUCTOR, GLOSSY, PLAIN, TEXTURED
from usplat_dr.io.images import colorize_depth, grid, save_png
from usplat_dr.io.names import safe_stem

#: The material classes the split reports (the codes of ``data.synth.render``).
MATERIALS = {"textured": TEXTURED, "plain": PLAIN, "glossy": GLOSSY, "conductor": CONDUCTOR}
#: Colours of the material map: miss black, textured orange, plain grey, glossy blue, metal gold.
MATERIAL_COLOURS = np.array([[0, 0, 0], [0.95, 0.55, 0.1], [0.7, 0.7, 0.7], [0.2, 0.45, 0.9],
                             [0.9, 0.8, 0.2]])
#: The columns ``allocation`` returns.
COLUMNS = ("kept", *(f"kept_{m}" for m in MATERIALS), "kept_near", "kept_far")


def kept_per_pixel(kept_mask: Bool[Tensor, "n g"], views: int, h: int, w: int
                   ) -> Float[Tensor, "v h w"]:
    """The fraction of the ``n`` targets (one scene's) that kept each context pixel's Gaussians
    (averaged over the pixel's Gaussians), from the Gaussians' order (view, pixel, Gaussian)."""
    n, g = kept_mask.shape
    if g % (views * h * w):
        raise ValueError(f"kept_mask has {g} Gaussians per target, not a multiple of "
                         f"{views} views x {h} x {w} pixels")
    return kept_mask.float().view(n, views, h, w, -1).mean((0, -1))


def allocation(kept: Float[Tensor, "v h w"], material: Float[Tensor, "v h w"] | None = None,
               depth: Float[Tensor, "v h w"] | None = None) -> dict[str, float]:
    """The kept fraction over all pixels (``kept``) and over the pixels of each material
    (``kept_textured``, ``kept_plain``, ...; NaN where the scene has none; material codes
    rounded, resizing blends them at edges) and of the near and far half (``kept_near``,
    ``kept_far``: at most / above the median of the finite, positive context depths). Keys
    without the map they need are left out."""
    def mean(sel: Tensor) -> float:
        return kept[sel].mean().item() if sel.any() else math.nan

    out = {"kept": kept.mean().item()}
    if material is not None:
        codes = material.round()
        out.update({f"kept_{name}": mean(codes == code) for name, code in MATERIALS.items()})
    if depth is not None:
        valid = torch.isfinite(depth) & (depth > 0)
        if valid.any():
            median = depth[valid].median()
            out["kept_near"] = mean(valid & (depth <= median))
            out["kept_far"] = mean(valid & (depth > median))
        else:
            out["kept_near"] = out["kept_far"] = math.nan
    return out


def save_allocation(folder: str | os.PathLike, batch: dict, kept: Float[Tensor, "v h w"],
                    prefix: str = "") -> Path:
    """A PNG of scene 0 of ``batch`` in ``folder``, a row per context view: the image, the
    fraction of targets that kept each pixel's Gaussians (white: all, black: none), its
    material (``MATERIAL_COLOURS``) and depth, where the data has them."""
    key = batch["scene"][0]
    context = batch["context"]
    rows = []
    for v, image in enumerate(context["image"][0]):
        row = [image.detach().clamp(0, 1).permute(1, 2, 0).cpu().numpy(),
               np.repeat(kept[v].cpu().numpy()[..., None], 3, -1)]
        if "material" in context:
            codes = context["material"][0, v].round().long().clamp(0, len(MATERIAL_COLOURS) - 1)
            row.append(MATERIAL_COLOURS[codes.cpu().numpy()])
        if "depth" in context:  # (+inf where the ray misses: black, as the background)
            d = context["depth"][0, v].cpu().numpy()
            hit = np.isfinite(d) & (d > 0)
            row.append(colorize_depth(np.where(hit, d, 0.0), hit.astype(float)))
        rows.append(row)
    return save_png(Path(folder) / f"{prefix}{safe_stem(key)}.png", grid(rows),
                    text={"scene": key})
