"""Figures of a model's predictions: the comparison sheet (context views, ground truth,
prediction and depth per target view)."""

import os
from pathlib import Path

from usplat_dr.io.images import colorize_depth, grid, save_png
from usplat_dr.io.names import safe_stem


def save_comparison(folder: str | os.PathLike, batch: dict, out, prefix: str = "") -> Path:
    """A PNG of scene 0 of ``batch`` in ``folder``: a row per target view with the context
    views, the ground truth, the prediction and its depth (``out``: a ``UniqueSplatOutput``).
    The file is named after the scene key made safe (``io.names.safe_stem``), after
    ``prefix``; the key itself is kept in the PNG's text (``scene``)."""
    key = batch["scene"][0]
    def img(t):
        return t.detach().clamp(0, 1).permute(1, 2, 0).cpu().numpy()

    ctx = [img(c) for c in batch["context"]["image"][0]]
    rows = [[*ctx, img(gt), img(out.color[0, j]),
             colorize_depth(out.depth[0, j].cpu().numpy(), out.alpha[0, j].cpu().numpy())]
            for j, gt in enumerate(batch["target"]["image"][0])]
    return save_png(Path(folder) / f"{prefix}{safe_stem(key)}.png", grid(rows),
                    text={"scene": key})
