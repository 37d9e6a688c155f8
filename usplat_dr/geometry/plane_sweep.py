"""A classical two-view plane sweep in numpy (Collins 1996; the cost volume MVSplat learns
from): the reference for depth from two photos, and the estimate of near/far for cameras
that come without sparse points.

For each depth hypothesis z (uniform in inverse depth), the reference view's pixels are
lifted to depth z, projected into the source view and its colour sampled there (bilinear);
the cost is the absolute colour difference summed over the channels and over a square
window (SAD). Each pixel takes the hypothesis of least cost. Conventions as in
``geometry.cameras``: camera-to-world OpenCV extrinsics, normalised intrinsics, pixel centres
at (j + 0.5, i + 0.5).
"""

import warnings
from dataclasses import dataclass

import numpy as np

#: near/far from a sweep: the depth percentiles of the confident pixels, widened by these
#: factors (as ``data.importers.near_far_from_points`` does for sparse points).
SWEEP_PERCENTILES = (1.0, 99.0)
SWEEP_MARGIN = (0.8, 1.2)
#: The share of the hypotheses at which the source must see a pixel for it to count as
#: confident (``SweepResult``).
SEEN_SHARE = 0.5


@dataclass
class SweepResult:
    """``depth`` [H, W] (camera-space z of the reference view), ``cost`` [H, W] (the least
    SAD), ``confident`` [H, W] bool (seen by the source at ``SEEN_SHARE`` of the hypotheses
    or more, converging cameras lose the nearest ones off the frame, and with a
    distinct minimum: its least cost below ``ratio`` times its median cost) and the
    ``depths`` swept [D]."""

    depth: np.ndarray
    cost: np.ndarray
    confident: np.ndarray
    depths: np.ndarray


def _box_sum(x: np.ndarray, window: int) -> np.ndarray:
    """The sum over a ``window`` x ``window`` square around each pixel of [..., H, W]
    (zero padding), by cumulative sums."""
    r = window // 2
    pad = np.pad(x, [(0, 0)] * (x.ndim - 2) + [(r + 1, r), (r + 1, r)])
    c = pad.cumsum(-1).cumsum(-2)
    return (c[..., window:, window:] - c[..., :-window, window:] - c[..., window:, :-window]
            + c[..., :-window, :-window])


def _bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``image`` [H, W, C] sampled at pixel coordinates (x, y) (continuous, pixel centres at
    +0.5) and whether each sample lies inside."""
    h, w = image.shape[:2]
    u, v = x - 0.5, y - 0.5
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    u, v = np.clip(u, 0, w - 1), np.clip(v, 0, h - 1)
    j0, i0 = np.minimum(np.floor(u).astype(int), w - 2), np.minimum(np.floor(v).astype(int),
                                                                     h - 2)
    fu, fv = (u - j0)[..., None], (v - i0)[..., None]
    out = (image[i0, j0] * (1 - fu) * (1 - fv) + image[i0, j0 + 1] * fu * (1 - fv)
           + image[i0 + 1, j0] * (1 - fu) * fv + image[i0 + 1, j0 + 1] * fu * fv)
    return out, inside


def plane_sweep(reference: np.ndarray, source: np.ndarray, intrinsics_ref: np.ndarray,
                intrinsics_src: np.ndarray, c2w_ref: np.ndarray, c2w_src: np.ndarray,
                depths: np.ndarray, window: int = 7, ratio: float = 0.8) -> SweepResult:
    """Depth of the ``reference`` view [H, W, C] (float, any range) from the ``source`` view
    [H', W', C] over the hypotheses ``depths`` [D] (module docstring).

    Examples:
        >>> rng = np.random.default_rng(0)
        >>> img = rng.random((24, 32, 3))
        >>> k = np.array([[1.0, 0, 0.5], [0, 32 / 24, 0.5], [0, 0, 1]])
        >>> src = np.roll(img, -2, axis=1)  # 2 px disparity: f 32 px, baseline 0.25 -> z 4
        >>> c2w_src = np.eye(4); c2w_src[0, 3] = 0.25
        >>> r = plane_sweep(img, src, k, k, np.eye(4), c2w_src, np.array([2.0, 4.0, 8.0]))
        >>> float(np.median(r.depth[:, 8:-8]))
        4.0
    """
    h, w = reference.shape[:2]
    hs, ws = source.shape[:2]
    k_ref = intrinsics_ref * np.array([[w], [h], [1.0]])  # pixels
    k_src = intrinsics_src * np.array([[ws], [hs], [1.0]])
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([jj, ii, np.ones_like(jj)], -1) @ np.linalg.inv(k_ref).T  # [H, W, 3], z=1
    ref_to_src = np.linalg.inv(c2w_src) @ c2w_ref
    rot, trans = ref_to_src[:3, :3], ref_to_src[:3, 3]
    costs = np.empty((len(depths), h, w))
    seen = np.zeros((h, w))
    for n, z in enumerate(depths):
        p = (rays * z) @ rot.T + trans  # [H, W, 3] in the source camera
        front = p[..., 2] > 1e-9
        zc = np.where(front, p[..., 2], 1.0)
        q = p / zc[..., None] @ k_src.T
        sampled, inside = _bilinear(source, q[..., 0], q[..., 1])
        valid = front & inside
        diff = np.abs(sampled - reference).sum(-1)
        costs[n] = _box_sum(np.where(valid, diff, 0.0), window) / np.maximum(
            _box_sum(valid.astype(np.float64), window), 1.0)
        costs[n][~valid] = np.inf
        seen += valid
    best = costs.argmin(0)
    least = np.take_along_axis(costs, best[None], 0)[0]
    finite = np.where(np.isfinite(costs), costs, np.nan)
    with warnings.catch_warnings():  # pixels no hypothesis sees: NaN, not confident
        warnings.simplefilter("ignore", RuntimeWarning)
        median = np.nanmedian(finite, axis=0) if len(depths) > 1 else least
    confident = (seen >= SEEN_SHARE * len(depths)) & np.isfinite(least) & (least < ratio * median)
    return SweepResult(depth=np.asarray(depths)[best], cost=least, confident=confident,
                       depths=np.asarray(depths))


def sweep_depths(intrinsics_ref: np.ndarray, width: int, c2w_ref: np.ndarray,
                 c2w_src: np.ndarray, count: int = 64, max_disparity: float = 0.5,
                 min_disparity_px: float = 0.5) -> np.ndarray:
    """``count`` depths uniform in inverse depth between a disparity of ``max_disparity`` of
    the image width and ``min_disparity_px`` pixels, for the two cameras' baseline (a plane
    farther than that moves less than half a pixel: no photometric cost can place it)."""
    baseline = float(np.linalg.norm(c2w_src[:3, 3] - c2w_ref[:3, 3]))
    if not baseline > 0:
        raise ValueError("the two cameras share a centre: a sweep needs a baseline")
    focal = float(intrinsics_ref[0, 0]) * width  # pixels
    near = focal * baseline / (max_disparity * width)
    far = focal * baseline / min_disparity_px
    return 1.0 / np.linspace(1.0 / near, 1.0 / far, count)


def near_far_from_sweep(images: list[np.ndarray], intrinsics: list[np.ndarray],
                        extrinsics: list[np.ndarray], long_side: int = 96, count: int = 64
                        ) -> tuple[float, float]:
    """(near, far) for two views without sparse points: a plane sweep each way between
    ``images`` [H, W, 3] (in [0, 1] or uint8) at ``long_side`` pixels, the
    ``SWEEP_PERCENTILES`` of the confident pixels' depths, widened by ``SWEEP_MARGIN``.
    A ``ValueError`` when too few pixels are confident (textureless views, no overlap)."""
    from PIL import Image  # a resize only

    small = []
    for im in images[:2]:
        h, w = im.shape[:2]
        s = long_side / max(h, w)
        size = (max(8, round(w * s)), max(8, round(h * s)))
        a = np.asarray(im if im.dtype == np.uint8 else (np.clip(im, 0, 1) * 255).round()
                       .astype(np.uint8))
        small.append(np.asarray(Image.fromarray(a).resize(size, Image.Resampling.BILINEAR),
                                dtype=np.float64) / 255.0)
    found = []
    for a, b in ((0, 1), (1, 0)):
        depths = sweep_depths(intrinsics[a], small[a].shape[1], extrinsics[a], extrinsics[b],
                              count)
        r = plane_sweep(small[a], small[b], intrinsics[a], intrinsics[b], extrinsics[a],
                        extrinsics[b], depths, window=5)
        found.append(r.depth[r.confident])
    depth = np.concatenate(found)
    total = sum(s.shape[0] * s.shape[1] for s in small)
    if depth.size < 0.02 * total:
        raise ValueError(f"the two context views match at {depth.size} of {total} pixels "
                         "(textureless, or not overlapping): give --near and --far")
    lo, hi = np.percentile(depth, SWEEP_PERCENTILES)
    return round(float(lo * SWEEP_MARGIN[0]), 6), round(float(hi * SWEEP_MARGIN[1]), 6)


def sweep_render(images: list[np.ndarray], intrinsics: list[np.ndarray],
                 extrinsics: list[np.ndarray], target_intrinsics: np.ndarray,
                 target_c2w: np.ndarray, shape: tuple[int, int], depths: np.ndarray,
                 window: int = 5) -> np.ndarray:
    """A novel view [H, W, C] of the target camera from two context views, classically: each
    target pixel is lifted to every depth of ``depths``, projected into both views (bilinear
    samples), and takes the depth where the two samples agree best (SAD over a ``window``
    square) and their mean colour there; a pixel only one view sees takes that view's sample,
    one neither sees 0. Conventions as ``plane_sweep``'s.

    Examples:
        >>> rng = np.random.default_rng(0)
        >>> img = rng.random((24, 32, 3))
        >>> k = np.array([[1.0, 0, 0.5], [0, 32 / 24, 0.5], [0, 0, 1]])
        >>> right = np.eye(4); right[0, 3] = 0.25  # 2 px of disparity at z 4 (f 32 px)
        >>> mid = np.eye(4); mid[0, 3] = 0.125
        >>> a, b = np.roll(img, 1, axis=1), np.roll(img, -1, axis=1)  # the plane z = 4
        >>> out = sweep_render([a, b], [k, k], [np.eye(4), right], k, mid, (24, 32),
        ...                    np.array([2.0, 4.0, 8.0]))
        >>> bool(np.abs(out[:, 3:-3] - img[:, 3:-3]).max() < 1e-9)
        True
    """
    h, w = shape
    k_t = target_intrinsics * np.array([[w], [h], [1.0]])
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([jj, ii, np.ones_like(jj)], -1) @ np.linalg.inv(k_t).T
    world_rays = rays @ target_c2w[:3, :3].T
    best_cost = np.full((h, w), np.inf)
    colour = np.zeros((h, w, images[0].shape[-1]))
    for z in depths:
        points = world_rays * z + target_c2w[:3, 3]
        samples, valid = [], []
        for image, k, c2w in zip(images[:2], intrinsics[:2], extrinsics[:2]):
            hs, ws = image.shape[:2]
            p = (points - c2w[:3, 3]) @ c2w[:3, :3]  # world -> camera (R^T (x - t))
            front = p[..., 2] > 1e-9
            q = p / np.where(front, p[..., 2], 1.0)[..., None] @ (
                k * np.array([[ws], [hs], [1.0]])).T
            s, inside = _bilinear(image, q[..., 0], q[..., 1])
            samples.append(s)
            valid.append(front & inside)
        both = valid[0] & valid[1]
        diff = np.abs(samples[0] - samples[1]).sum(-1)
        cost = _box_sum(np.where(both, diff, 0.0), window) / np.maximum(
            _box_sum(both.astype(np.float64), window), 1.0)
        cost = np.where(both, cost, np.inf)
        better = cost < best_cost
        best_cost = np.where(better, cost, best_cost)
        colour = np.where(better[..., None], (samples[0] + samples[1]) / 2, colour)
        for s, v, other in ((samples[0], valid[0], valid[1]), (samples[1], valid[1], valid[0])):
            alone = ~np.isfinite(best_cost) & v & ~other  # seen by one view only, so far
            colour = np.where(alone[..., None], s, colour)
    return colour
