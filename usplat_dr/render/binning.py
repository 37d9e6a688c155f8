"""Binning: which Gaussians each tile composites, in depth order (Dr.Jit, not differentiable).

The reference (3DGS ``getRect``/``duplicateWithKeys``) considers a Gaussian at a pixel only if
the square of half-width ``radius`` around its centre overlaps the pixel's 16x16 tile. Smaller
tiles refine that set without changing the image: a Gaussian stays in a T x T tile when its
16x16 parent tile is in the reference rectangle and, with ``opacity_cull``, when the ellipse on
which it can reach ``alpha >= 1/255`` overlaps the tile (elsewhere the reference skips it by its
own ``alpha < 1/255`` rule). Pairs are generated in global depth order and stably bucket-sorted by
tile, so each tile's list is depth-sorted with ties in index order, as the reference's radix sort.
"""

from dataclasses import dataclass

import drjit as dr

from usplat_dr.render.project import Projected
from usplat_dr.render.settings import REFERENCE_TILE

#: Compositing skips a Gaussian at a pixel where its alpha is below this (3DGS).
ALPHA_MIN = 1.0 / 255.0
#: Opacity culling is used only for conics with cond(2D covariance) = a c / det below this: the
#: float32 power's rounding error grows with the condition number, and the box margin below is
#: sized for errors up to ~1e-4 relative (3 eps x cond).
MAX_CULL_CONDITION = 1.0e3


@dataclass
class Bins:
    """Per-tile lists. ``pair_gid`` (``UInt32``, one lane per (tile, Gaussian) pair, tile-major,
    depth order within a tile): Gaussian index. ``tile_start``, ``tile_end`` (``UInt32``, one lane
    per tile of every image): the range of each tile in ``pair_gid``. ``num_pairs`` (``int``, or
    ``None`` with a fixed capacity, which reads nothing back). With a fixed capacity,
    ``overflow`` (``Bool``, one lane): the scene needed more pair lanes than the capacity;
    ``needed`` (``UInt32``, one lane): how many it needed; ``kept`` (``UInt32``, one lane): the
    pairs in tile ranges (``num_pairs`` without the host read). Without a capacity, ``needed`` is
    the number of candidate pairs (``int``) and the other two are ``None``.
    """

    pair_gid: object
    tile_start: object
    tile_end: object
    num_pairs: int | None
    overflow: object = None
    needed: object = None
    kept: object = None


def tile_rects(p: Projected, tile_size: int, opacity_cull: bool, width, height, grid_x, grid_y):
    """Tile rectangle ``[x0, x1) x [y0, y1)`` (``UInt32``, in tiles of ``tile_size``), pair
    count (``UInt32``) and cull bound (``Float``) of every Gaussian.

    The cull bound ``q_max`` is such that the Gaussian can reach ``alpha >= 1/255`` only where
    ``d^T conic d <= q_max`` (``inf`` when opacity culling is off or unsafe for this Gaussian).

    Parameter ``width, height`` (``Float``, opaque scalars): image size in pixels. ``grid_x,
    grid_y`` (``Float``, opaque scalars): number of ``tile_size`` tiles across and down.
    """
    UInt32 = dr.uint32_array_t(type(p.u))
    u, v = dr.detach(p.u), dr.detach(p.v)
    valid = dr.detach(p.valid)
    # The reference's pixel frame: centre p = u - 0.5 against integer pixel indices.
    px = dr.select(valid, u - 0.5, 0.0)
    py = dr.select(valid, v - 0.5, 0.0)
    r = dr.select(valid, p.radius, 0.0)

    # ---- Reference rectangle on the 16x16 grid (getRect), clamped to the grid ----
    # Clamping before floor equals the reference's int-truncate-then-clamp, and keeps huge or
    # infinite coordinates out of the float -> int conversion.
    ref = float(REFERENCE_TILE)
    grid16_x = dr.ceil(width / ref)
    grid16_y = dr.ceil(height / ref)
    x0 = dr.floor(dr.clip((px - r) / ref, 0.0, grid16_x))
    x1 = dr.floor(dr.clip((px + r + (ref - 1.0)) / ref, 0.0, grid16_x))
    y0 = dr.floor(dr.clip((py - r) / ref, 0.0, grid16_y))
    y1 = dr.floor(dr.clip((py + r + (ref - 1.0)) / ref, 0.0, grid16_y))
    valid &= (x1 > x0) & (y1 > y0)

    # ---- Refine to tile_size tiles (tile_size divides 16) ----
    sub = float(REFERENCE_TILE // tile_size)
    x0, y0 = x0 * sub, y0 * sub
    x1 = dr.minimum(x1 * sub, grid_x)
    y1 = dr.minimum(y1 * sub, grid_y)

    q_max = dr.full(type(u), dr.inf, dr.width(u))
    if opacity_cull:
        o = dr.detach(p.opacity)
        # alpha = min(0.99, o G) <= o: below 1/255 everywhere when o is.
        valid &= o >= ALPHA_MIN
        a, b, c = p.cov2d
        well_conditioned = a * c <= MAX_CULL_CONDITION * (a * c - b * b)
        # o exp(power) >= 1/255  <=>  d^T Sigma^-1 d <= 2 ln(255 o): an ellipse whose bounding box
        # has half-extents sqrt(2 ln(255 o) Sigma_xx), sqrt(2 ln(255 o) Sigma_yy). Widened for
        # float32 rounding: +1e-4 on the log covers absolute errors in power/exp/o x exp, 1 %
        # covers relative errors of the power (<= ~3e-4 at the condition bound), +0.01 px the rest.
        reach = 2.0 * (dr.log(dr.maximum(o, ALPHA_MIN) * 255.0) + 1e-4)
        ext_x = dr.sqrt(reach * a) * 1.01 + 0.01
        ext_y = dr.sqrt(reach * c) * 1.01 + 0.01
        ts = float(tile_size)
        bx0 = dr.floor(dr.clip((px - ext_x) / ts, 0.0, grid_x))
        bx1 = dr.floor(dr.clip((px + ext_x) / ts + 1.0, 0.0, grid_x))
        by0 = dr.floor(dr.clip((py - ext_y) / ts, 0.0, grid_y))
        by1 = dr.floor(dr.clip((py + ext_y) / ts + 1.0, 0.0, grid_y))
        x0 = dr.select(well_conditioned, dr.maximum(x0, bx0), x0)
        x1 = dr.select(well_conditioned, dr.minimum(x1, bx1), x1)
        y0 = dr.select(well_conditioned, dr.maximum(y0, by0), y0)
        y1 = dr.select(well_conditioned, dr.minimum(y1, by1), y1)
        q_max = dr.select(well_conditioned, reach * 1.02, dr.inf)

    valid &= (x1 > x0) & (y1 > y0)
    x0, x1, y0, y1 = (UInt32(q) for q in (x0, x1, y0, y1))
    count = dr.select(valid, (x1 - x0) * (y1 - y0), 0)
    return x0, x1, y0, y1, count, q_max


def _min_quadratic_over_box(ca, cb, cc, dx_lo, dx_hi, dy_lo, dy_hi):
    """min of q(d) = ca dx^2 + 2 cb dx dy + cc dy^2 (positive definite) over a box of d.

    Zero when the box holds d = 0; otherwise the minimum lies on an edge, where q is a 1D
    quadratic minimised at the clamped stationary point.
    """
    def q(dx, dy):
        return dr.fma(ca, dx * dx, dr.fma(2.0 * cb, dx * dy, cc * (dy * dy)))

    inv_ca, inv_cc = dr.rcp(ca), dr.rcp(cc)
    best = dr.inf
    for dx in (dx_lo, dx_hi):
        best = dr.minimum(best, q(dx, dr.clip(-cb * dx * inv_cc, dy_lo, dy_hi)))
    for dy in (dy_lo, dy_hi):
        best = dr.minimum(best, q(dr.clip(-cb * dy * inv_ca, dx_lo, dx_hi), dy))
    inside = (dx_lo <= 0) & (dx_hi >= 0) & (dy_lo <= 0) & (dy_hi >= 0)
    return dr.select(inside, 0.0, best)


def stable_bucket_order(bucket, size: int, buckets: int):
    """The permutation that sorts ``bucket`` (``UInt32`` values < ``buckets``), keeping the input
    order within each bucket.

    On LLVM, Dr.Jit's ``block_mkperm`` (one counting sort) is stable and as fast as a radix
    sort here. On CUDA, Dr.Jit 1.5's ``block_mkperm`` with many buckets is not stable, although
    documented so: on an H200, with 4,096 buckets, the order within buckets broke from ~300,000
    entries on (16,853 inversions in 300,000), which would composite a tile's Gaussians out of
    depth order. CUDA uses ``dr.argsort`` instead, whose radix passes call ``block_mkperm`` with
    256 buckets each, and which stayed stable up to the 3,000,000 entries tested there.
    """
    if dr.backend_v(bucket) == dr.JitBackend.CUDA:
        return dr.argsort(bucket)
    return dr.detail.block_mkperm(bucket, size, buckets)


def bin_gaussians(p: Projected, x0, x1, y0, y1, count, q_max, tile_size: int, tile_base,
                  grid_x, num_tiles: int, capacity: int | None = None) -> Bins:
    """Expand Gaussians into (tile, Gaussian) pairs and sort them by tile, then depth.

    Parameter ``p`` (``Projected``): centres and conics (read detached) and depth (sort key).
    Parameter ``x0, x1, y0, y1, count, q_max`` (one lane per Gaussian): from ``tile_rects``.
    ``tile_base`` (``UInt32``): index of the Gaussian's image's first tile. ``grid_x``
    (``UInt32``, opaque scalar): tiles across. ``num_tiles`` (``int``): tiles over all images.

    A pair is kept only if the ellipse ``d^T conic d <= q_max`` meets the rectangle of the tile's
    pixel samples (exact test of a convex quadratic over a box); the others would be skipped at
    every pixel of the tile by the reference's ``alpha < 1/255`` rule. Two host reads (numbers
    of candidate and kept pairs, to size the pair arrays).

    Parameter ``capacity`` (``int`` or ``None``): with a number, the pair arrays have that many
    lanes whatever the scene needs and nothing is read back to the host (so the whole render can
    be recorded by ``dr.freeze``): lanes past the scene's candidate pairs are masked, dropped pairs
    stay at the end of ``pair_gid`` (no tile range reaches them), and ``Bins.overflow`` (``Bool``,
    one lane) is true when the scene needed more candidate lanes than ``capacity`` (its images
    then miss pairs: render again with ``Bins.needed``, ``UInt32``, one lane, or more).
    """
    if capacity is not None:
        return _bin_fixed(p, x0, x1, y0, y1, count, q_max, tile_size, tile_base, grid_x,
                          num_tiles, capacity)
    UInt32 = type(count)
    perm, count_sorted, end = _depth_order(p, count)
    num_pairs = int(end[dr.width(count) - 1])

    tile_count = dr.zeros(UInt32, num_tiles)
    if num_pairs == 0:
        return Bins(pair_gid=dr.zeros(UInt32, 1), tile_start=tile_count, tile_end=tile_count,
                    num_pairs=0, needed=0)
    begin = end - count_sorted
    gid, tile, keep = _pairs(p, perm, begin, count_sorted, num_pairs, x0, x1, y0, q_max,
                             tile_size, tile_base, grid_x)

    # ---- Stable bucket sort by tile keeps the depth order within each tile; dropped pairs go
    # to one bucket behind all tiles ----
    bucket = dr.select(keep, tile, num_tiles)
    dr.eval(bucket, gid)  # one pair-generation kernel for both consumers below
    perm_tile, tile_start, tile_end = _sort_by_tile(bucket, num_pairs, num_tiles)
    num_kept = int(tile_end[num_tiles - 1])
    if num_kept == 0:
        return Bins(pair_gid=dr.zeros(UInt32, 1), tile_start=tile_start, tile_end=tile_end,
                    num_pairs=0, needed=num_pairs)
    kept = dr.gather(UInt32, perm_tile, dr.arange(UInt32, num_kept))
    pair_gid = dr.gather(UInt32, gid, kept)
    return Bins(pair_gid=pair_gid, tile_start=tile_start, tile_end=tile_end, num_pairs=num_kept,
                needed=num_pairs)


def _depth_order(p: Projected, count):
    """Gaussians in global depth order (stable radix sort; culled ones, count 0, last): the
    permutation, their pair counts in that order and the inclusive sum of those counts."""
    perm = dr.argsort(dr.select(count > 0, dr.detach(p.z), dr.inf))
    count_sorted = dr.gather(type(count), count, perm)
    return perm, count_sorted, dr.prefix_reduce(dr.ReduceOp.Add, count_sorted, exclusive=False)


def _pairs(p: Projected, perm, begin, count_sorted, size: int, x0, x1, y0, q_max,
           tile_size: int, tile_base, grid_x):
    """Gaussian index, tile and keep flag of ``size`` pair lanes (Gaussians in depth order
    ``perm``, each owning ``count_sorted`` lanes from ``begin``; a Gaussian whose first lane is
    at or past ``size`` owns none)."""
    UInt32 = type(begin)
    n = dr.width(begin)
    # ---- Pair owners: scatter each Gaussian's sorted position at its first pair, max-scan ----
    owner = dr.zeros(UInt32, size)
    dr.scatter(owner, dr.arange(UInt32, n), begin, active=count_sorted > 0)
    owner = dr.prefix_reduce(dr.ReduceOp.Max, owner, exclusive=False)
    gid = dr.gather(UInt32, perm, owner)

    # ---- Tile of each pair (row-major within the Gaussian's rectangle) ----
    k = dr.arange(UInt32, size) - dr.gather(UInt32, begin, owner)
    gx0 = dr.gather(UInt32, x0, gid)
    gy0 = dr.gather(UInt32, y0, gid)
    # Guarded divisor: masked tail lanes of a packet may read 0 and trap
    # (docs/rasteriser_notes.md, "Integer division in kernels").
    w = dr.maximum(dr.gather(UInt32, x1, gid) - gx0, 1)
    # row = k // w without an integer division (scalarised on SIMD CPUs: 16 divisions per
    # packet; the kernel ran 13.3 -> 10.1-10.9 ms at 256x256): (k + 0.5) / w is never an
    # integer, and in float32 its floor is within one of the quotient while k < 2^24 (a
    # rectangle of 16.7M tiles); the two integer checks below make the row exact.
    Float = type(p.u)
    row = UInt32(dr.floor((Float(k) + 0.5) / Float(w)))
    row = dr.select(row * w > k, row - 1, row)
    row = dr.select((row + 1) * w <= k, row + 1, row)
    tx = gx0 + (k - row * w)
    ty = gy0 + row
    tile = dr.gather(UInt32, tile_base, gid) + ty * grid_x + tx

    # ---- Exact ellipse-vs-tile test (pixel samples at tile origin + 0.5 .. + T - 0.5) ----
    q_bound = dr.gather(Float, q_max, gid)
    u = dr.gather(Float, dr.detach(p.u), gid)
    v = dr.gather(Float, dr.detach(p.v), gid)
    ca, cb, cc = (dr.gather(Float, dr.detach(c), gid) for c in p.conic)
    first_x = Float(tx * tile_size) + 0.5
    first_y = Float(ty * tile_size) + 0.5
    span = float(tile_size - 1)
    q_min = _min_quadratic_over_box(ca, cb, cc, u - first_x - span, u - first_x,
                                    v - first_y - span, v - first_y)
    return gid, tile, q_min <= q_bound


def _sort_by_tile(bucket, size: int, num_tiles: int):
    """Stable order of ``size`` pair lanes by ``bucket`` (tile, or ``num_tiles`` for a dropped
    pair) and each tile's range ``[tile_start, tile_end)`` in that order."""
    UInt32 = type(bucket)
    buckets = 1 << num_tiles.bit_length()  # a power of two > num_tiles
    perm_tile = stable_bucket_order(bucket, size, buckets)
    tile_count = dr.zeros(UInt32, num_tiles)
    dr.scatter_reduce(dr.ReduceOp.Add, tile_count, UInt32(1), bucket, active=bucket < num_tiles,
                      mode=dr.ReduceMode.Direct)
    tile_end = dr.prefix_reduce(dr.ReduceOp.Add, tile_count, exclusive=False)
    return perm_tile, tile_end - tile_count, tile_end


def _bin_fixed(p: Projected, x0, x1, y0, y1, count, q_max, tile_size: int, tile_base, grid_x,
               num_tiles: int, capacity: int) -> Bins:
    """``bin_gaussians`` with ``capacity`` pair lanes and no host read (see there)."""
    UInt32 = type(count)
    perm, count_sorted, end = _depth_order(p, count)
    begin = end - count_sorted
    needed = dr.gather(UInt32, end, dr.opaque(UInt32, dr.width(end) - 1))  # one lane
    # A Gaussian owns the lanes [begin, end) that fit; one starting past the capacity owns none.
    fits = count_sorted > 0
    fits &= begin < capacity
    gid, tile, keep = _pairs(p, perm, begin, dr.select(fits, count_sorted, 0), capacity, x0, x1,
                             y0, q_max, tile_size, tile_base, grid_x)
    keep &= dr.arange(UInt32, capacity) < needed  # lanes past the scene's pairs
    bucket = dr.select(keep, tile, num_tiles)
    dr.eval(bucket, gid)
    perm_tile, tile_start, tile_end = _sort_by_tile(bucket, capacity, num_tiles)
    kept = dr.gather(UInt32, tile_end, dr.opaque(UInt32, num_tiles - 1))
    return Bins(pair_gid=dr.gather(UInt32, gid, perm_tile), tile_start=tile_start,
                tile_end=tile_end, num_pairs=None, overflow=needed > capacity, needed=needed,
                kept=kept)
