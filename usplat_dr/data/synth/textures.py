"""Textures in numpy (deterministic for a seed), stored in scene descriptions as small
JSON-able specs and rebuilt on demand: procedural ones ``{"pattern": ..., "seed": ...,
"colors": ...}`` and photographic ones ``{"pattern": "photo", "image": ..., ...}`` (a random
crop of one of scikit-image's photographs, rotated, scaled and jittered in colour and
contrast: ``photo_texture_spec``)."""

import functools

import numpy as np
from PIL import Image

PATTERNS = ("checker", "stripes", "noise", "bricks", "dots")
#: The photographs of ``skimage.data`` (shipped with scikit-image, nothing downloaded) that
#: photographic textures crop: natural surfaces (brick, grass, gravel, moon), scenes and
#: objects (astronaut, camera, coffee, cat, rocket, coins, clock), micrographs (cell,
#: immunohistochemistry), print (text, page). Not the retina and the Hubble field (mostly
#: black surround), nor the Middlebury motorcycle: that stereo pair scores the models' depth
#: on a real photograph.
PHOTOS = ("astronaut", "brick", "camera", "cat", "coffee", "coins", "grass", "gravel",
          "rocket", "moon", "text", "page", "cell", "immunohistochemistry", "clock")


@functools.lru_cache(maxsize=len(PHOTOS))
def photo(name: str) -> np.ndarray:
    """float64 [H, W, 3] in [0, 1] of ``skimage.data.<name>()`` (grey ones repeated)."""
    if name not in PHOTOS:
        raise ValueError(f"photo must be one of {PHOTOS}, got {name!r}")
    import skimage.data  # on first use (start-up time)

    a = np.asarray(getattr(skimage.data, name)(), dtype=np.float64) / 255.0
    return np.repeat(a[..., None], 3, -1) if a.ndim == 2 else a[..., :3]


def photo_texture_spec(rng: np.random.Generator, res: int = 256) -> dict:
    """A random photographic texture: a photograph, the crop's side (a fraction of its
    shorter side) and centre, a rotation, a tint (for grey photos), gain, contrast and
    saturation."""
    return {"pattern": "photo", "image": PHOTOS[int(rng.integers(len(PHOTOS)))],
            "res": res, "crop": round(float(rng.uniform(0.15, 0.9)), 3),
            "centre": rng.uniform(0.0, 1.0, 2).round(3).tolist(),
            "rotation": round(float(rng.uniform(0, 360)), 1),
            "tint": (0.55 + 0.45 * rng.random(3)).round(3).tolist(),
            "gain": round(float(rng.uniform(0.55, 1.15)), 3),
            "contrast": round(float(rng.uniform(0.6, 1.3)), 3),
            "saturation": round(float(rng.uniform(0.4, 1.3)), 3)}


def _photo_texture(spec: dict) -> np.ndarray:
    """The float64 [res, res, 3] image of a ``photo_texture_spec``."""
    src = photo(spec["image"])
    h, w = src.shape[:2]
    side = max(8, round(spec["crop"] * min(h, w)))
    # a window 1.5x the crop, rotated, then the crop's centre: no corners outside the photo
    big = min(round(side * 1.5), h, w)
    cy = round(spec["centre"][1] * (h - big))
    cx = round(spec["centre"][0] * (w - big))
    window = Image.fromarray((src[cy:cy + big, cx:cx + big] * 255).round().astype(np.uint8))
    window = window.rotate(spec["rotation"], resample=Image.Resampling.BILINEAR)
    off = (big - min(side, round(big / 1.5))) // 2
    cut = big - 2 * off
    window = window.crop((off, off, off + cut, off + cut)).resize(
        (spec["res"], spec["res"]), Image.Resampling.LANCZOS)
    img = np.asarray(window, dtype=np.float64) / 255.0
    grey = img.mean(-1, keepdims=True)
    if np.allclose(src[..., 0], src[..., 1]):  # a grey photo: tinted
        img = grey * np.asarray(spec["tint"])
    img = grey + spec["saturation"] * (img - grey)
    img = img.mean() + spec["contrast"] * (img - img.mean())
    return img * spec["gain"]


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
    if spec["pattern"] == "photo":
        return (np.clip(_photo_texture(spec), 0, 1) * 255 + 0.5).astype(np.uint8)
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


def make_environment(spec: dict) -> np.ndarray:
    """The float32 [h, w, 3] linear-radiance equirectangular image of an environment spec
    ``{"seed", "res": [h, w], "scale", "version"}`` (row 0 the zenith, +Y up as Mitsuba's
    ``envmap``; ``version``: the scene description's, 1 if absent):
    a sky gradient with clouds above the horizon, darker ground with bands below, a sun glow
    and bright rectangular panels (windows, buildings), so that mirror-like surfaces reflect
    a structured surrounding that changes with the viewpoint.

    Examples:
        >>> env = make_environment({"seed": 1, "res": [8, 16], "scale": 1.0})
        >>> env.shape, env.dtype, bool((env > 0).all())
        ((8, 16, 3), dtype('float32'), True)
    """
    rng = np.random.default_rng(spec["seed"])
    h, w = spec["res"]
    theta = (np.arange(h) + 0.5) / h * np.pi  # from the zenith
    phi = (np.arange(w) + 0.5) / w * 2 * np.pi
    up = np.cos(theta)[:, None, None]  # 1 at the zenith, -1 at the nadir
    zenith, horizon = np.array([0.25, 0.4, 0.8]), np.array([0.85, 0.9, 1.0])
    ground = (0.15 + 0.2 * rng.random(3)) * np.array([1.0, 0.9, 0.75])
    t = np.clip(up, 0, 1) ** 0.5
    img = np.where(up > 0, zenith * t + horizon * (1 - t), ground) * np.ones((1, w, 1))
    clouds = _value_noise(rng, max(h, w), 6)[:h, :w, None]
    img = np.where(up > 0, img * (0.75 + 0.5 * clouds), img * (0.7 + 0.6 * (
        np.sin(phi * int(rng.integers(3, 9)))[None, :, None] > 0)))
    sun_t, sun_p = rng.uniform(0.15, 0.4) * np.pi, rng.uniform(0, 2 * np.pi)
    cos_angle = (np.cos(theta)[:, None] * np.cos(sun_t) + np.sin(theta)[:, None] * np.sin(sun_t)
                 * np.cos(phi[None] - sun_p))
    # The description's version 2 (the view-dependent appearance's second version) has a
    # softer sun and more panels than version 1; a stored description re-renders as it was.
    v2 = spec.get("version", 1) >= 2
    sun, width, panels = (3.0, 0.02, (6, 13)) if v2 else (6.0, 0.01, (3, 7))
    img = img + sun * np.exp((cos_angle - 1) / width)[..., None] * np.array([1.0, 0.95, 0.85])
    for _ in range(int(rng.integers(*panels))):  # bright panels around the horizon
        r0 = int(rng.integers(h // 4, h // 2))
        r1 = r0 + int(rng.integers(2, max(3, h // 5)))
        c0 = int(rng.integers(0, w))
        cols = (c0 + np.arange(int(rng.integers(2, max(3, w // 8))))) % w
        img[r0:r1, cols] = 1.5 + 2.5 * rng.random(3)
    return (img * spec["scale"]).astype(np.float32)
