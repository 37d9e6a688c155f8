"""Writing renders as images: PNG (atomically), depth colour maps, contact sheets."""

import json
import os
from pathlib import Path

import numpy as np
from PIL import Image
from PIL.PngImagePlugin import PngInfo

from usplat_dr.io.atomic import atomic_open

# Control points of a perceptually ordered colour map (dark blue -> teal -> yellow), after
# matplotlib's viridis; linear interpolation between them is enough for depth previews.
_CMAP = np.array([[0.267, 0.005, 0.329], [0.283, 0.141, 0.458], [0.254, 0.265, 0.530],
                  [0.207, 0.372, 0.553], [0.164, 0.471, 0.558], [0.128, 0.567, 0.551],
                  [0.135, 0.659, 0.518], [0.267, 0.749, 0.441], [0.478, 0.821, 0.318],
                  [0.741, 0.873, 0.150], [0.993, 0.906, 0.144]])


def to_uint8(image: np.ndarray) -> np.ndarray:
    """[H, W] or [H, W, 3] floats in [0, 1] (clipped) to uint8."""
    return (np.clip(np.nan_to_num(image), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def colorize_depth(depth: np.ndarray, alpha: np.ndarray | None = None, near: float | None = None,
                   far: float | None = None) -> np.ndarray:
    """[H, W] depth to [H, W, 3] colours (near bright, far dark, background black).

    ``depth`` is the rasteriser's alpha-weighted depth; dividing by ``alpha`` (where given and
    > 1e-3) recovers the expected depth of the visible surface.
    """
    d = depth.astype(np.float64)
    mask = np.ones_like(d, dtype=bool) if alpha is None else alpha > 1e-3
    if alpha is not None:
        d = np.where(mask, d / np.maximum(alpha, 1e-3), 0.0)
    if not mask.any():
        return np.zeros((*d.shape, 3))
    lo = np.percentile(d[mask], 1) if near is None else near
    hi = np.percentile(d[mask], 99) if far is None else far
    # Inverse depth spreads near structure over more of the map (as the field's depth videos).
    inv = 1.0 / np.maximum(d, 1e-6)
    t = (inv - 1.0 / hi) / max(1.0 / lo - 1.0 / hi, 1e-12)
    t = np.clip(np.nan_to_num(t), 0.0, 1.0) * (len(_CMAP) - 1)
    i = np.minimum(t.astype(int), len(_CMAP) - 2)
    f = (t - i)[..., None]
    rgb = _CMAP[i] * (1 - f) + _CMAP[i + 1] * f
    return np.where(mask[..., None], rgb, 0.0)


def save_png(path: str | os.PathLike, image: np.ndarray,
             text: dict[str, str] | None = None) -> Path:
    """Write [H, W] or [H, W, 3] floats in [0, 1] as PNG, atomically (temp file + rename).

    ``text``: PNG text entries (``{"scene": key}`` keeps a scene's key inside its file; values
    are stored JSON-quoted, so any string, NUL bytes included, survives)."""
    info = None
    if text:
        info = PngInfo()
        for k, v in text.items():
            info.add_itxt(k, json.dumps(v))
    with atomic_open(path, "wb") as f:
        Image.fromarray(to_uint8(image)).save(f, format="PNG", pnginfo=info)
    return Path(path)


def grid(rows: list[list[np.ndarray]], pad: int = 4) -> np.ndarray:
    """Tile equally sized [H, W, 3] images into one contact sheet with white padding."""
    h, w = rows[0][0].shape[:2]
    n_cols = max(len(r) for r in rows)
    sheet = np.ones((len(rows) * (h + pad) + pad, n_cols * (w + pad) + pad, 3))
    for r, row in enumerate(rows):
        for c, img in enumerate(row):
            y, x = pad + r * (h + pad), pad + c * (w + pad)
            sheet[y:y + h, x:x + w] = img if img.ndim == 3 else img[..., None]
    return sheet
