"""Figures of a model's predictions: the comparison sheet (context views, ground truth,
prediction and depth per target view)."""

import os
from pathlib import Path

from usplat_dr.io.images import colorize_depth, grid, save_png


def save_comparison(path: str | os.PathLike, batch: dict, out) -> Path:
    """A PNG of scene 0 of ``batch``: a row per target view with the context views, the
    ground truth, the prediction and its depth (``out``: a ``UniqueSplatOutput``)."""
    def img(t):
        return t.detach().clamp(0, 1).permute(1, 2, 0).cpu().numpy()

    ctx = [img(c) for c in batch["context"]["image"][0]]
    rows = [[*ctx, img(gt), img(out.color[0, j]),
             colorize_depth(out.depth[0, j].cpu().numpy(), out.alpha[0, j].cpu().numpy())]
            for j, gt in enumerate(batch["target"]["image"][0])]
    return save_png(path, grid(rows))
