"""Per-target pruning before rasterisation: model no more Gaussians than a view needs.

Two kinds of pruning, chosen in ``PruneSettings``:

- **Culling** (``cull``, exact): drop the Gaussians the rasteriser would skip anyway for this
  camera: centre at or behind ``0.2 near``, a degenerate 2D covariance, opacity below 1/255
  (alpha = opacity x exp(-power) can never reach the 1/255 compositing threshold), and
  footprints whose 16x16-tile rectangle (the reference's ``getRect`` with its 3-sigma radius)
  does not meet the image, and footprints whose alpha >= 1/255 ellipse contains no pixel
  centre of the image (one pixel of margin). The render is unchanged; the rasteriser sorts
  and bins fewer Gaussians, and their memory is not carried.
- **Merging** (``merge``, approximate): two context views that see the same surface predict
  near-duplicate Gaussians. Gaussians that fall in the same cell of ``merge_pixels`` target
  pixels, the same relative depth bin (``merge_depth``) and the same colour bin
  (``merge_color``, on the DC colour) are replaced by one moment-matched Gaussian: opacity
  1 - prod(1 - o_i) (the coverage of the stack at its centre), mean, covariance (spread of the
  means included) and SH coefficients weighted by opacity.

Keeping a number of Gaussians is the model's Gaussian budget (``model/budget.py``,
``GaussianBudget``); its ``"footprint"`` ranking scores with ``footprint_scores`` here: opacity
x screen-space area for the target camera, after the culling rule.

Pruned sets differ in size per target; ``prune`` pads them to the largest with Gaussians at
the camera centre with opacity 0, which the rasteriser culls before any per-pixel work.
"""

from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

#: Constants of the rasteriser (``usplat_dr.render.project``) that decide what it skips.
from usplat_dr.render.project import COV2D_DILATION, FRUSTUM_GUARD, NEAR_CULL

ALPHA_MIN = 1.0 / 255.0
REFERENCE_TILE = 16  # the reference's tile rectangle (getRect) decides which tiles a splat meets
SH_C0 = 0.28209479177387814  # degree-0 real SH constant (same in the 3DGS and e3nn bases)


@dataclass(frozen=True)
class PruneSettings:
    """What to prune per target view. ``PruneSettings()`` is exact culling only (renders
    unchanged); ``PruneSettings(merge=True)`` also merges near-duplicates."""

    cull: bool = True
    merge: bool = False
    merge_pixels: float = 1.0  # cell edge in target pixels
    merge_depth: float = 0.02  # relative depth bin width (log-depth bins)
    merge_color: float = 0.1  # DC colour bin width (colour in [0, 1])
    #: Retired (2026-11-27): a value here is an error naming its replacement, the Gaussian
    #: budget's footprint ranking.
    keep_fraction: float | None = None

    def __post_init__(self):
        if self.keep_fraction is not None:
            raise ValueError(f"PruneSettings.keep_fraction is retired: keep fewer Gaussians with "
                             f"a budget, forward(..., budget=GaussianBudget("
                             f"{self.keep_fraction}, rank_by='footprint')) "
                             f"(usplat_dr.model.budget), --gaussians and --rank-by footprint "
                             f"on the command line")
        if self.merge_pixels <= 0 or self.merge_depth <= 0 or self.merge_color <= 0:
            raise ValueError("PruneSettings: merge_pixels, merge_depth and merge_color must be "
                             f"> 0, got {self.merge_pixels}, {self.merge_depth}, "
                             f"{self.merge_color}")

    @property
    def exact(self) -> bool:
        return not self.merge

    def label(self) -> str:
        parts = ["cull" if self.cull else "all"]
        if self.merge:
            parts.append(f"merge{self.merge_pixels:g}px")
        return "+".join(parts)


#: Named settings, from rendering every Gaussian (``"all"``: no pruning) through exact culling
#: to merging: the pruning axis of ``usplat bench`` (its ``--gaussians`` the budget axis), also
#: timed by train/bench/prune.py.
PRUNES: dict[str, PruneSettings | None] = {
    "all": None,
    "cull": PruneSettings(),
    "cull+merge1px": PruneSettings(merge=True),
    "cull+merge2px": PruneSettings(merge=True, merge_pixels=2.0),
}


@dataclass
class Pruned:
    """The pruned, padded Gaussians ([B, K, ...]) and ``counts`` [B]: how many are real."""

    means: Tensor
    covariances: Tensor
    harmonics: Tensor
    opacities: Tensor
    counts: Tensor


def screen_footprint(extrinsics: Float[Tensor, "b 4 4"], intrinsics: Float[Tensor, "b 3 3"],
                     near: Float[Tensor, " b"], image_shape: tuple[int, int],
                     means: Float[Tensor, "b g 3"], covariances: Float[Tensor, "b g 3 3"]
                     ) -> dict[str, Tensor]:
    """Pixel centre ``u, v``, camera depth ``z``, the dilated 2D covariance (``a, b, c``),
    the 3-sigma ``radius`` and ``valid`` (in front of 0.2 near, positive determinant), as the
    rasteriser computes them (``project.project``; float32 like it)."""
    h, w = image_shape
    w2c = torch.linalg.inv(extrinsics.double()).to(means.dtype)
    r, t = w2c[:, None, :3, :3], w2c[:, None, :3, 3]
    p = (r @ means[..., None])[..., 0] + t
    valid = p[..., 2] > NEAR_CULL * near[:, None]
    z = torch.where(valid, p[..., 2], torch.ones_like(p[..., 2]))
    x_z, y_z = p[..., 0] / z, p[..., 1] / z
    fx, fy = intrinsics[:, 0, 0, None] * w, intrinsics[:, 1, 1, None] * h
    cx, cy = intrinsics[:, 0, 2, None] * w, intrinsics[:, 1, 2, None] * h
    guard = FRUSTUM_GUARD - 1.0
    x_c = torch.minimum(torch.maximum(x_z, -(cx + guard * 0.5 * w) / fx),
                        (w - cx + guard * 0.5 * w) / fx)
    y_c = torch.minimum(torch.maximum(y_z, -(cy + guard * 0.5 * h) / fy),
                        (h - cy + guard * 0.5 * h) / fy)
    zeros = torch.zeros_like(z)
    jac = torch.stack([torch.stack([fx / z, zeros, -fx * x_c / z], -1),
                       torch.stack([zeros, fy / z, -fy * y_c / z], -1)], -2)  # [b, g, 2, 3]
    tm = jac @ r
    cov2 = tm @ covariances @ tm.transpose(-1, -2)
    a = cov2[..., 0, 0] + COV2D_DILATION
    b = cov2[..., 0, 1]
    c = cov2[..., 1, 1] + COV2D_DILATION
    det = a * c - b * b
    valid &= det > 0
    mid = 0.5 * (a + c)
    lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
    radius = torch.ceil(3.0 * torch.sqrt(lam.clamp(min=0)))
    valid &= torch.isfinite(radius)
    return {"u": fx * x_z + cx, "v": fy * y_z + cy, "z": z, "a": a, "b": b, "c": c,
            "det": det, "radius": radius, "valid": valid}


def _meets_image(centre: Tensor, radius: Tensor, size: int) -> Tensor:
    """The reference's tile rectangle (getRect, as ``binning.tile_rects``) along one axis is
    not empty: tiles [lo, hi) of 16 pixels, centre in its pixel frame (u - 0.5)."""
    grid = -(-size // REFERENCE_TILE)
    p = centre - 0.5
    lo = torch.floor(torch.clamp((p - radius) / REFERENCE_TILE, 0, grid))
    hi = torch.floor(torch.clamp((p + radius + REFERENCE_TILE - 1) / REFERENCE_TILE, 0, grid))
    return hi > lo


def _reaches_pixels(centre: Tensor, extent: Tensor, size: int) -> Tensor:
    """The ellipse where alpha >= 1/255 (half-extent ``extent`` along this axis) contains a
    pixel centre (0.5 .. size - 0.5) of this axis, with a one-pixel margin for rounding."""
    return (centre + extent > -0.5) & (centre - extent < size + 0.5)


@torch.no_grad()
def prune(extrinsics: Float[Tensor, "b 4 4"], intrinsics: Float[Tensor, "b 3 3"],
          near: Float[Tensor, " b"], image_shape: tuple[int, int],
          means: Float[Tensor, "b g 3"], covariances: Float[Tensor, "b g 3 3"],
          harmonics: Float[Tensor, "b g 3 d"], opacities: Float[Tensor, "b g"],
          settings: PruneSettings) -> Pruned:
    """Prune each batch entry's Gaussians for its camera (see the module docstring).

    Inference only (no gradients): culling drops nothing that renders, so training gains
    nothing from it, and merging is not meant to be differentiated.
    """
    bsz = opacities.shape[0]
    fp = screen_footprint(extrinsics, intrinsics, near, image_shape, means, covariances)
    keep = torch.ones_like(opacities, dtype=torch.bool)
    if settings.cull:
        keep = _visible(fp, opacities, image_shape)
    batch_idx, gauss_idx = keep.nonzero(as_tuple=True)
    sel = dict(means=means[batch_idx, gauss_idx], cov=covariances[batch_idx, gauss_idx],
               sh=harmonics[batch_idx, gauss_idx], opacity=opacities[batch_idx, gauss_idx])
    if settings.merge and len(batch_idx):
        sel, batch_idx = _merge(sel, batch_idx, {k: v[batch_idx, gauss_idx]
                                                 for k, v in fp.items()}, settings)
    return _pad(sel, batch_idx, bsz, extrinsics)


def _visible(fp: dict, opacities: Tensor, image_shape: tuple[int, int]) -> Tensor:
    """The culling rule (module docstring): what the rasteriser would composite somewhere."""
    h, w = image_shape
    # alpha = o exp(-q / 2) >= 1/255 inside d^T conic d <= q_max = 2 ln(255 o), an ellipse
    # with half-extents sqrt(q_max a) and sqrt(q_max c) (a, c: the 2D covariance diagonal)
    q_max = 2 * torch.log((opacities * 255).clamp(min=1))
    return (fp["valid"] & (opacities >= ALPHA_MIN)
            & _meets_image(fp["u"], fp["radius"], w) & _meets_image(fp["v"], fp["radius"], h)
            & _reaches_pixels(fp["u"], (q_max * fp["a"]).sqrt(), w)
            & _reaches_pixels(fp["v"], (q_max * fp["c"]).sqrt(), h))


@torch.no_grad()
def footprint_scores(extrinsics: Float[Tensor, "b 4 4"], intrinsics: Float[Tensor, "b 3 3"],
                     near: Float[Tensor, " b"], image_shape: tuple[int, int],
                     means: Float[Tensor, "b g 3"], covariances: Float[Tensor, "b g 3 3"],
                     opacities: Float[Tensor, "b g"]) -> Float[Tensor, "b g"]:
    """How much of each batch entry's image a Gaussian covers: opacity x the area of its
    3-sigma ellipse (clipped at the image's area), -1 where the culling rule drops it (the
    budget's ``"footprint"`` ranking, ``model/budget.py``)."""
    h, w = image_shape
    fp = screen_footprint(extrinsics, intrinsics, near, image_shape, means, covariances)
    area = (torch.pi * fp["det"].clamp(min=0).sqrt() * 9).clamp(max=h * w)
    return torch.where(_visible(fp, opacities, image_shape), opacities * area,
                       torch.full_like(area, -1.0))


def moment_match(group: Tensor, n: int, means: Tensor, covariances: Tensor, harmonics: Tensor,
                 opacities: Tensor) -> dict[str, Tensor]:
    """The Gaussians of each of ``n`` groups (``group`` [M]: each Gaussian's group) merged into
    one, [n, ...]: the opacity-weighted mean and covariance (the members' covariances plus the
    spread of their means), the opacity-weighted SH, and the opacity of the members stacked,
    ``1 - prod(1 - o)``. A group without members gets zeros."""

    def gsum(x: Tensor) -> Tensor:
        out = torch.zeros((n, *x.shape[1:]), dtype=x.dtype, device=x.device)
        return out.index_add_(0, group, x)

    o = opacities
    wsum = gsum(o).clamp(min=1e-12)  # every kept Gaussian has o >= 1/255 when culling

    def wmean(x: Tensor) -> Tensor:
        shape = (-1,) + (1,) * (x.dim() - 1)
        return gsum(o.view(shape) * x) / wsum.view(shape)

    mean = wmean(means)
    d = means - mean[group]
    return {"means": mean, "covariances": wmean(covariances + d[:, :, None] * d[:, None, :]),
            "harmonics": wmean(harmonics),
            "opacities": 1 - torch.exp(gsum(torch.log1p(-o.clamp(max=1 - 1e-6))))}


def _merge(sel: dict, batch_idx: Tensor, fp: dict, s: PruneSettings) -> tuple[dict, Tensor]:
    colour = (SH_C0 * sel["sh"][..., 0] + 0.5).clamp(0, 1)
    # one int64 key per Gaussian (a 1D unique is a fast sort): batch 10 bits, cell x and y 12
    # bits each, log-depth bin 14, colour bins 4 x 3. Cells are clamped to the ranges, which
    # only ever merges Gaussians far outside the image (culled first by default).
    if int(batch_idx.max()) >= 1 << 10:
        raise ValueError("prune(merge=True) handles at most 1024 images per call")
    fields = [(batch_idx, 10),
              (torch.floor(fp["u"] / s.merge_pixels).long() + 1024, 12),
              (torch.floor(fp["v"] / s.merge_pixels).long() + 1024, 12),
              (torch.floor(torch.log(fp["z"]) / s.merge_depth).long() + (1 << 13), 14),
              *((torch.floor(ch / s.merge_color).long(), 4) for ch in colour.unbind(-1))]
    key = torch.zeros_like(batch_idx)
    for value, bits in fields:
        key = (key << bits) | value.clamp(0, (1 << bits) - 1)
    _, group = torch.unique(key, return_inverse=True)
    n = int(group.max()) + 1
    merged = moment_match(group, n, sel["means"], sel["cov"], sel["sh"], sel["opacity"])
    # the batch index is part of the key: one value per group
    out_batch = torch.zeros(n, dtype=batch_idx.dtype, device=group.device).scatter_(
        0, group, batch_idx)
    return dict(means=merged["means"], cov=merged["covariances"], sh=merged["harmonics"],
                opacity=merged["opacities"]), out_batch


def _pad(sel: dict, batch_idx: Tensor, bsz: int, extrinsics: Tensor) -> Pruned:
    counts = torch.bincount(batch_idx, minlength=bsz)
    k = max(int(counts.max()) if len(counts) else 0, 1)
    order = torch.argsort(batch_idx, stable=True)
    batch_sorted = batch_idx[order]
    starts = torch.cumsum(counts, 0) - counts
    slot = torch.arange(len(batch_sorted), device=batch_idx.device) - starts[batch_sorted]
    ref = sel["means"]
    like = dict(dtype=ref.dtype, device=ref.device)
    means = extrinsics[:, None, :3, 3].expand(bsz, k, 3).to(**like).clone()
    cov = torch.zeros((bsz, k, 3, 3), **like)
    cov[..., 0, 0] = cov[..., 1, 1] = cov[..., 2, 2] = 1e-6  # positive definite padding
    sh = torch.zeros((bsz, k, *sel["sh"].shape[1:]), **like)
    opacity = torch.zeros((bsz, k), **like)
    for dst, src in ((means, sel["means"]), (cov, sel["cov"]), (sh, sel["sh"]),
                     (opacity, sel["opacity"])):
        dst[batch_sorted, slot] = src[order]
    return Pruned(means=means, covariances=cov, harmonics=sh, opacities=opacity, counts=counts)
