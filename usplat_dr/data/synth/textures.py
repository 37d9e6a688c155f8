"""Procedural textures in numpy (deterministic for a seed), stored in scene descriptions as
small JSON-able specs ``{"pattern": ..., "seed": ..., "colors": ...}`` and rebuilt on demand."""

import numpy as np

PATTERNS = ("checker", "stripes", "noise", "bricks", "dots")


def _value_noise(rng: np.random.Generator, res: int, cells: int) -> np.ndarray:
    """Smooth noise in [0, 1]: a random ``cells`` x ``cells`` grid, bilinearly interpolated
    with wrap-around (so textures tile)."""
    grid = rng.random((cells, cells))
    t = np.arange(res) * cells / res
    i0 = np.floor(t).astype(int)
    f = t - i0
    f = f * f * (3 - 2 * f)  # smoothstep: no visible grid lines
    i1 = (i0 + 1) % cells
    a = grid[i0][:, i0] * (1 - f)[None] + grid[i0][:, i1] * f[None]
    b = grid[i1][:, i0] * (1 - f)[None] + grid[i1][:, i1] * f[None]
    return a * (1 - f)[:, None] + b * f[:, None]


def random_texture_spec(rng: np.random.Generator, res: int = 128) -> dict:
    """A random texture spec: a pattern and two or three colours."""
    pattern = PATTERNS[int(rng.integers(len(PATTERNS)))]
    colors = (0.15 + 0.8 * rng.random((3, 3))).round(3).tolist()
    return {"pattern": pattern, "seed": int(rng.integers(2**31)), "colors": colors, "res": res,
            "cells": int(rng.integers(3, 9))}


def make_texture(spec: dict) -> np.ndarray:
    """Build the uint8 [res, res, 3] sRGB image of a texture spec.

    Examples:
        >>> rng = np.random.default_rng(0)
        >>> spec = random_texture_spec(rng, res=16)
        >>> img = make_texture(spec)
        >>> img.shape, img.dtype, bool((make_texture(spec) == img).all())
        ((16, 16, 3), dtype('uint8'), True)
    """
    rng = np.random.default_rng(spec["seed"])
    res, cells = spec["res"], spec["cells"]
    c = np.asarray(spec["colors"], dtype=np.float64)
    y, x = np.mgrid[0:res, 0:res] / res
    pattern = spec["pattern"]
    if pattern == "checker":
        m = ((np.floor(x * cells) + np.floor(y * cells)) % 2)[..., None]
        img = c[0] * m + c[1] * (1 - m)
    elif pattern == "stripes":
        m = (0.5 + 0.5 * np.sin(2 * np.pi * cells * (x + 0.3 * y)))[..., None]
        img = c[0] * m + c[1] * (1 - m)
    elif pattern == "noise":
        n1 = _value_noise(rng, res, cells)[..., None]
        n2 = _value_noise(rng, res, cells * 4)[..., None]
        img = c[0] * n1 + c[1] * (1 - n1)
        img = img * (0.7 + 0.3 * n2) + c[2] * 0.3 * (1 - n2)
    elif pattern == "bricks":
        rows = np.floor(y * cells)
        shift = (rows % 2) * 0.5
        u = x * cells / 2 + shift
        mortar = (np.abs(y * cells - np.round(y * cells)) < 0.06) | (np.abs(u - np.round(u)) < 0.04)
        jitter = _value_noise(rng, res, cells * 2)[..., None]
        img = np.where(mortar[..., None], c[2], c[0] * jitter + c[1] * (1 - jitter))
    elif pattern == "dots":
        fx, fy = (x * cells) % 1 - 0.5, (y * cells) % 1 - 0.5
        m = ((fx * fx + fy * fy) < 0.09)[..., None]
        n = _value_noise(rng, res, cells)[..., None]
        img = np.where(m, c[0], c[1] * (0.6 + 0.4 * n))
    else:
        raise ValueError(f"pattern must be one of {PATTERNS}, got {pattern!r}")
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
