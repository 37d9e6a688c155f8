"""Evaluation index files for synthetic sets: a standard split and stress splits where
feed-forward methods fail. Each is an index JSON in the field's format (scene key -> null or
{"context": [i, j], "target": [...]}), chosen from the known cameras, depths and materials."""

import math

import numpy as np

from usplat_dr.data.synth.render import PLAIN, SHINY
from usplat_dr.geometry.cameras import pixel_directions

SPLITS = ("standard", "wide_baseline", "extrapolation", "large_rotation", "disocclusion",
          "textureless", "glossy")

# Thresholds for a scene to enter a stress split (fractions of target pixels / degrees).
MIN_ROTATION_DEG = 30.0
MIN_DISOCCLUDED = 0.02
MIN_TEXTURELESS = 0.10
MIN_GLOSSY = 0.01


def _between(left: int, right: int, n: int) -> list[int]:
    inner = list(range(left + 1, right))
    if len(inner) <= n:
        return inner or [left, right][:n]
    return sorted({inner[round(k)] for k in np.linspace(0, len(inner) - 1, n + 2)[1:-1]})


def rotation_deg(c2w_a: np.ndarray, c2w_b: np.ndarray) -> float:
    """Angle of the relative rotation between two cameras, in degrees."""
    r = c2w_a[:3, :3].T @ c2w_b[:3, :3]
    return math.degrees(math.acos(np.clip((np.trace(r) - 1) / 2, -1, 1)))


def disoccluded_fraction(target: int, contexts: list[int], c2w: np.ndarray, intr: np.ndarray,
                         depths: np.ndarray) -> float:
    """Fraction of the target's visible surface seen by none of the context views (outside
    their frame or hidden behind nearer geometry): what the contexts cannot show."""
    h, w = depths.shape[1:]
    d = depths[target]
    hit = np.isfinite(d)
    if not hit.any():
        return 0.0
    p_cam = np.concatenate([pixel_directions(intr, (h, w)) * d[..., None],
                            np.ones((h, w, 1))], -1)[hit]  # [N, 4]
    p_world = p_cam @ c2w[target].T
    seen = np.zeros(len(p_world), dtype=bool)
    for c in contexts:
        q = p_world @ np.linalg.inv(c2w[c]).T
        z = q[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (q[:, 0] / z * intr[0, 0] + intr[0, 2]) * w
            v = (q[:, 1] / z * intr[1, 1] + intr[1, 2]) * h
        inside = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        zc = np.full(len(z), np.inf)
        zc[inside] = depths[c][v[inside].astype(int), u[inside].astype(int)]
        # Visible when no surface in the context view is clearly in front (2% of the depth
        # absorbs the pixel discretisation of the context depth map).
        seen |= inside & (zc >= z * 0.98)
    return float(1.0 - seen.mean())


def scene_splits(c2w: np.ndarray, intr: np.ndarray, depths: np.ndarray,
                 materials: np.ndarray, rng: np.random.Generator) -> tuple[dict, dict]:
    """Entries of every split for one scene (None where the scene does not qualify) and the
    measurements behind them."""
    v = len(c2w)
    out: dict = {s: None for s in SPLITS}
    stats: dict = {}
    if v < 3:
        return out, stats
    gap = max(2, round(v / 3))
    left = int(rng.integers(0, v - gap))
    std = {"context": [left, left + gap], "target": _between(left, left + gap, 3)}
    out["standard"] = std
    out["wide_baseline"] = {"context": [0, v - 1], "target": _between(0, v - 1, 3)}
    g = max(2, round(v / 4))
    left_e = (v - g) // 2
    outside = sorted({max(0, left_e - g // 2 - 1), max(0, left_e - 1),
                      min(v - 1, left_e + g + 1), min(v - 1, left_e + g + g // 2 + 1)}
                     - set(range(left_e, left_e + g + 1)))
    if outside:
        out["extrapolation"] = {"context": [left_e, left_e + g], "target": outside}

    pairs = [(rotation_deg(c2w[i], c2w[j]), i, j) for i in range(v) for j in range(i + 2, v)]
    best = max(pairs)
    stats["max_rotation_deg"] = round(best[0], 2)
    if best[0] >= MIN_ROTATION_DEG:
        # The narrowest pair that still rotates enough: a rotation, not just a wide baseline.
        i, j = min(((j - i, i, j) for a, i, j in pairs if a >= MIN_ROTATION_DEG))[1:]
        out["large_rotation"] = {"context": [i, j], "target": _between(i, j, 3)}

    candidates = list(range(std["context"][0] + 1, std["context"][1]))
    dis = {t: disoccluded_fraction(t, std["context"], c2w, intr, depths) for t in candidates}
    top = sorted(candidates, key=lambda t: -dis[t])[:3]
    stats["disoccluded"] = round(max(dis.values(), default=0.0), 4)
    if top and dis[top[0]] >= MIN_DISOCCLUDED:
        out["disocclusion"] = {"context": std["context"], "target": sorted(top)}

    for name, codes, threshold in (("textureless", (PLAIN,), MIN_TEXTURELESS),
                                   ("glossy", SHINY, MIN_GLOSSY)):
        frac = {t: float(np.isin(materials[t], codes).mean()) for t in candidates}
        top = sorted(candidates, key=lambda t: -frac[t])[:3]
        stats[name] = round(max(frac.values(), default=0.0), 4)
        if top and frac[top[0]] >= threshold:
            out[name] = {"context": std["context"], "target": sorted(top)}
    return out, stats
