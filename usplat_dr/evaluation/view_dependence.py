"""How view-dependent a synthetic set is, measured from its ground truth alone.

Each context view is warped into each target view with the true depths (a pixel of the target
is unprojected at its true depth, projected into the context view and read there bilinearly)
and compared with the true target on the pixels both views see, per material class of the
target pixel. On a matte (Lambertian) surface the radiance does not depend on the viewpoint,
so the warp differs from the target only by resampling and render noise: the diffuse class
sits at that floor. Glossy and metallic pixels fall below it by as much as their appearance
changes between the two viewpoints: the gap is what a view-dependent model can win and what a
shared set of Gaussians with low-order colour cannot represent.

A pixel counts as co-visible when its point lies in front of the context camera, inside its
frame, and all four pixels the bilinear read touches hold that point's depth within
``rel_tol`` (5 %: float16 depths are exact to 0.05 %, and neighbouring pixels of one smooth
surface differ by a few % at 64x64 on slanted floors, while a silhouette or an occluder
differs by far more).

Examples:
    >>> import numpy as np
    >>> k = np.array([[0.5, 0, 0.5], [0, 0.5, 0.5], [0, 0, 1]])
    >>> depth = np.full((4, 4), 2.0)
    >>> image = np.random.default_rng(0).random((4, 4, 3))
    >>> warped, valid = warp_into(depth, np.eye(4), k, image, depth, np.eye(4), k)
    >>> bool(valid.all()), bool(np.allclose(warped, image))  # a view warped into itself
    (True, True)
"""

import itertools
import math
import os
from pathlib import Path

import numpy as np

from usplat_dr.data.chunks import cameras_to_matrices, decode_image, read_chunk, stage_chunks
from usplat_dr.data.synth.render import CONDUCTOR, GLOSSY, MATTE
from usplat_dr.geometry.cameras import pixel_directions
from usplat_dr.io.images import save_png
from usplat_dr.io.names import safe_stem

#: Material classes of the meter: name -> material codes of ``usplat synth``'s maps.
CLASSES = {"diffuse": MATTE, "glossy": (GLOSSY,), "metal": (CONDUCTOR,)}
#: A scene's class enters the mean only with at least this many co-visible pixels (over all
#: its target-context pairs): fewer make a noisy PSNR.
MIN_PIXELS = 50


def warp_into(target_depth: np.ndarray, target_c2w: np.ndarray, target_k: np.ndarray,
              image: np.ndarray, depth: np.ndarray, c2w: np.ndarray, k: np.ndarray,
              rel_tol: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """A source view (``image`` [h, w, C], camera-space z ``depth`` [h, w], OpenCV ``c2w``,
    normalised ``k``) seen from the target camera: [H, W, C] values read bilinearly at each
    target pixel's true point (``target_depth`` [H, W], z, +inf on a miss) and the [H, W]
    mask of the co-visible pixels (module docstring); masked-out values are 0."""
    th, tw = target_depth.shape
    h, w = depth.shape
    finite = np.isfinite(target_depth)
    z_t = np.where(finite, target_depth, 1.0)
    points = pixel_directions(target_k, (th, tw)) * z_t[..., None]  # target camera space
    c2w_t, c2w_s = np.asarray(target_c2w, np.float64), np.asarray(c2w, np.float64)
    world = points @ c2w_t[:3, :3].T + c2w_t[:3, 3]
    cam = (world - c2w_s[:3, 3]) @ c2w_s[:3, :3]  # R^T (X - t), row vectors
    z = cam[..., 2]
    front = finite & (z > 1e-9)
    z_safe = np.where(front, z, 1.0)
    # normalised image coordinates -> pixel coordinates with pixel i's centre at i
    u = (k[0, 0] * cam[..., 0] / z_safe + k[0, 2]) * w - 0.5
    v = (k[1, 1] * cam[..., 1] / z_safe + k[1, 2]) * h - 0.5
    inside = front & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    j0 = np.clip(np.floor(u), 0, w - 2).astype(int) if w > 1 else np.zeros_like(u, int)
    i0 = np.clip(np.floor(v), 0, h - 2).astype(int) if h > 1 else np.zeros_like(v, int)
    fu, fv = np.clip(u - j0, 0, 1), np.clip(v - i0, 0, 1)
    taps = [(i0, j0, (1 - fv) * (1 - fu)), (i0, j0 + 1, (1 - fv) * fu),
            (i0 + 1, j0, fv * (1 - fu)), (i0 + 1, j0 + 1, fv * fu)]
    valid = inside
    out = np.zeros((th, tw, image.shape[-1]))
    for i, j, weight in taps:
        i, j = np.minimum(i, h - 1), np.minimum(j, w - 1)
        d = depth[i, j]
        valid = valid & np.isfinite(d) & (np.abs(d - z) <= rel_tol * z_safe)
        out += weight[..., None] * image[i, j]
    return np.where(valid[..., None], out, 0.0), valid


def indexed_scenes(root: str | os.PathLike, index: dict, stage: str = "test"):
    """The chunk records of a set that ``index`` evaluates, with their entries, in chunk
    order: ``(scene, entry)`` pairs."""
    for chunk in stage_chunks([root], stage):
        for scene in read_chunk(chunk):
            entry = index.get(scene["key"])
            if entry is not None:
                yield scene, entry


def scene_errors(scene: dict, entry: dict, rel_tol: float = 0.05) -> dict[str, list]:
    """Squared-error sum and pixel count per class (``[sse, n]``) of a chunk record's context
    views warped into its target views (``entry``: an evaluation index entry)."""
    c2w, k = (t.double().numpy() for t in cameras_to_matrices(scene["cameras"]))
    depths = scene["depths"].float().numpy()
    materials = scene["materials"].numpy()
    images = {i: decode_image(scene["images"][i]).permute(1, 2, 0).numpy() / 255.0
              for i in {*entry["context"], *entry["target"]}}
    out = {name: [0.0, 0] for name in CLASSES}
    for t in entry["target"]:
        for c in entry["context"]:
            warped, valid = warp_into(depths[t], c2w[t], k[t], images[c], depths[c], c2w[c],
                                      k[c], rel_tol)
            err = ((warped - images[t]) ** 2).mean(-1)
            for name, codes in CLASSES.items():
                m = valid & np.isin(materials[t], codes)
                out[name][0] += float(err[m].sum())
                out[name][1] += int(m.sum())
    return out


def psnr_of(sse: float, n: int) -> float:
    """PSNR (images in [0, 1]) of a squared-error sum over ``n`` values; NaN when n = 0."""
    if n == 0:
        return float("nan")
    return -10.0 * math.log10(max(sse / n, 1e-12))


def meter(root: str | os.PathLike, index: dict, stage: str = "test",
          rel_tol: float = 0.05) -> dict:
    """The warp PSNR per class over a set: per scene (``scenes``: key -> class -> {psnr,
    pixels}) and summarised (``classes``: class -> mean PSNR over the scenes with at least
    ``MIN_PIXELS`` co-visible pixels of it, their number, and the PSNR of all such pixels
    pooled). ``index``: scene key -> {"context", "target"} (an evaluation index)."""
    per_scene = {}
    for scene, entry in indexed_scenes(root, index, stage):
        errs = scene_errors(scene, entry, rel_tol)
        per_scene[scene["key"]] = {name: {"psnr": psnr_of(*e), "pixels": e[1], "sse": e[0]}
                                   for name, e in errs.items()}
    classes = {}
    for name in CLASSES:
        kept = [s[name] for s in per_scene.values() if s[name]["pixels"] >= MIN_PIXELS]
        classes[name] = {
            "psnr": float(np.mean([s["psnr"] for s in kept])) if kept else float("nan"),
            "scenes": len(kept),
            "pooled_psnr": psnr_of(sum(s["sse"] for s in kept), sum(s["pixels"] for s in kept)),
            "pixels": sum(s["pixels"] for s in kept)}
    return {"scenes": per_scene, "classes": classes}


def paired_gap(result: dict, low: str = "glossy", high: str = "diffuse") -> dict:
    """``high`` minus ``low`` warp PSNR over the scenes that have both classes (each with
    ``MIN_PIXELS``): the mean gap and the number of scenes."""
    gaps = [s[high]["psnr"] - s[low]["psnr"] for s in result["scenes"].values()
            if s[high]["pixels"] >= MIN_PIXELS and s[low]["pixels"] >= MIN_PIXELS]
    return {"mean": float(np.mean(gaps)) if gaps else float("nan"), "scenes": len(gaps)}


def noise_floor(root: str | os.PathLike, index: dict, scenes: int, spp: int,
                stage: str = "test") -> dict:
    """The render noise per class: the first target view of ``scenes`` scenes rendered again
    by Mitsuba from the stored description with another sample seed (``spp`` samples, as the
    set was), against the stored image. A warp of a pixel cannot score above this. Returns
    class -> {psnr (pooled over the scenes), pixels}."""
    from usplat_dr.data.synth.render import render_spec  # Mitsuba: only when measuring noise

    sse = {name: [0.0, 0] for name in CLASSES}
    for scene, entry in itertools.islice(indexed_scenes(root, index, stage), scenes):
        t = entry["target"][0]
        stored = decode_image(scene["images"][t]).permute(1, 2, 0).numpy() / 255.0
        spec = scene["mitsuba"]
        again = render_spec(spec, stored.shape[:2], spp=spp, seed=int(spec["seed"]) + 1,
                            frames=[t])[0][0] / 255.0
        err = ((again - stored) ** 2).mean(-1)
        for name, codes in CLASSES.items():
            m = np.isin(scene["materials"].numpy()[t], codes)
            sse[name][0] += float(err[m].sum())
            sse[name][1] += int(m.sum())
    return {name: {"psnr": psnr_of(*e), "pixels": e[1]} for name, e in sse.items()}


def write_error_images(root: str | os.PathLike, index: dict, out: str | os.PathLike,
                       scenes: int = 4, stage: str = "test") -> list[Path]:
    """Per scene a PNG: target, context warped into it, their absolute difference (x4) and
    the material map, for the first target and context of ``scenes`` scenes."""
    palette = np.array([[0, 0, 0], [0.55, 0.55, 0.55], [0.8, 0.8, 0.8], [0.2, 0.5, 1.0],
                        [1.0, 0.7, 0.1]])  # miss, textured, plain, glossy, metal
    written = []
    for scene, entry in itertools.islice(indexed_scenes(root, index, stage), scenes):
        c2w, k = (x.double().numpy() for x in cameras_to_matrices(scene["cameras"]))
        t, c = entry["target"][0], entry["context"][0]
        img = {i: decode_image(scene["images"][i]).permute(1, 2, 0).numpy() / 255.0
               for i in (t, c)}
        depths = scene["depths"].float().numpy()
        warped, valid = warp_into(depths[t], c2w[t], k[t], img[c], depths[c], c2w[c], k[c])
        diff = np.clip(4 * np.abs(warped - img[t]), 0, 1) * valid[..., None]
        mats = palette[np.clip(scene["materials"].numpy()[t], 0, len(palette) - 1)]
        path = Path(out) / f"{safe_stem(scene['key'])}.png"
        save_png(path, np.concatenate([img[t], warped, diff, mats], 1),
                 text={"scene": scene["key"]})
        written.append(path)
    return written
