"""A Gaussian budget chosen at inference: keep the K most important Gaussians of each target's
set and adapt the kept ones to the budget (EcoSplat, Park et al., arXiv 2512.18692: a
pixel-aligned feed-forward model fine-tuned to rank its primitives and rescale them for any K).

``UniqueSplat.forward(..., budget=K)`` calls ``apply_budget`` on the Gaussians of each target
(B N sets of G). ``K`` is a count (an int >= 1; one at least G keeps every Gaussian) or a
fraction in (0, 1] (``budget_count``). ``rank_by`` chooses the ranking:

- ``"learned"``: ordered dithering of a learned density. The importance head (``ImportanceHead``,
  on the Gaussian head's input) gives a log-density r per Gaussian, added to the log of its
  opacity (the prior, detached: the head's last convolution starts at zero); the score adds
  ``-log T``, T in (0, 1) the Bayer threshold of the Gaussian's pixel (``dither_offsets``, an
  8x8 tile). Keeping the top K is then keeping a Gaussian where ``c o e^r > T`` for the one c
  that keeps K: where the density is uniform the kept pixels are spread evenly (every other
  pixel at 1/4 of them) instead of a contiguous blob. A convolution sees no position, so its
  logits alone are nearly equal on a textureless wall and a top-K of them would keep one end of
  the wall and drop the other; the dither spreads them, and the head only has to learn how
  dense each region must be (textured more than flat, one context view's copy of a surface
  less where the other view has it). Learned scores only rank: the opacities are not changed
  by them.
- ``"dither"``: the same with no head (r = 0) and the adaptation's coverage rule alone: what the
  untrained head does (bit for bit), so that ``"learned"`` against ``"dither"`` is what the
  training added, and what a model without the head does by default.
- ``"footprint"``: how much of the target's image each Gaussian covers, opacity x the area of
  its 3-sigma ellipse for the target camera, those the rasteriser would skip last
  (``render.prune.footprint_scores``): the rule-based ranking of pruning, per target view.
- ``"opacity"`` and ``"random"`` (seeded): the controls of ``usplat bench``'s chart.

Selection is per set, the K highest scores, ties to the lower index (a stable descending sort:
the same as ``numpy.argsort(-scores, kind="stable")[:K]``); the kept Gaussians keep their order
(view-major, pixel in raster order), so ``out.target(b, n)`` is a set of K in the usual layout.

Adaptation (``"learned"`` and ``"dither"``): each kept Gaussian stands in for the dropped ones
around it. With f the fraction kept among the Gaussians of the ``LOCAL_WINDOW`` pixels around
it (``local_fraction``, counted in its context view's image), it takes ``log_copies`` a and
``log_scale`` s and becomes ``opacity' = 1 - (1 - opacity)^(e^a)``, the coverage of e^a stacked
copies of it (the merge rule of ``render/prune.py``), written as
``o + (1 - o) (1 - (1 - o)^(e^a - 1))`` so that a = 0 gives ``o`` exactly, and its 3D scales
times e^s (covariance times e^2s). a and s start at the coverage rule, a = -log f (1/f copies)
and s = -log(f) / 2 (an area 1/f times larger), plus a residual a tiny MLP of (log K/G, log f,
F per-Gaussian features from the importance head) learns, its last layer starting at zero.
Where nothing around is dropped (f = 1, and so at any budget that keeps everything) the rule is
the identity. The rule rather than the identity as the start: on the shipped (c) at 64x64 (8
held-out scenes of the standard split, untrained head) keeping 10% / 30% / 50% gave 10.9 /
16.4 / 21.1 dB with the identity and 19.0 / 22.9 / 25.2 dB with the rule, against 25.3 dB for
all of them (and 8.8 / 11.4 / 14.6 dB for the top by opacity). f is counted rather than
inferred from the density (``c o e^r``, exact only where the density is smooth over a dither
tile): a trained head's logits vary from pixel to pixel, and the inferred f misjudged them.

Training (``budget_tau``): the hard top-K passes no gradient to the scores, so training uses a
relaxation (``soft_mask``). Its value: the K kept Gaussians render as inference renders them
(adapted, full opacity), and every dropped one stays, unadapted, with its opacity times
``sigmoid((score - t) / tau)`` (< 1/2), t midway between the K-th and (K+1)-th highest score;
a dropped Gaussian near the threshold then shows a little, so the loss can ask for it back (a
straight-through top-K drops it outright, and the rasteriser gives a Gaussian of opacity 0 no
gradient: on the shipped (c), 300 steps, it learnt less than this). Its gradient: that
sigmoid's for all of them, with t moving as a budget of K requires (``soft_mask``: the mask's
sum cannot change, so a gradient trades one Gaussian for another; with t fixed, "more opacity
here" holds almost everywhere, every score drifted up and the trained ranking lost to the
untrained one). As tau -> 0 it becomes the hard mask where the K-th and (K+1)-th scores
differ (tested), so the trainer anneals tau geometrically (``train.budget_tau``). K >= G (a
fraction of 1) changes nothing at all: the output is the unbudgeted model's, bit for bit.
"""

import math
import numbers
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float, Int
from torch import Tensor, nn

from usplat_dr.model.types import Gaussians

#: The rankings ``apply_budget`` knows.
RANKINGS = ("learned", "dither", "footprint", "opacity", "random")
#: Per-Gaussian features the importance head gives the adaptation, beside its logit.
ADAPT_FEATURES = 4
#: Bounds of the adaptation's outputs: at most e^3 ~ 20 copies' coverage, scales within
#: e^+-2 ~ 7.4x (a budget of 5% has ~4.5x fewer Gaussians along each image axis), and the
#: learned residual on the coverage rule within e^+-1.
MAX_LOG_COPIES = 3.0
MAX_LOG_SCALE = 2.0
MAX_RESIDUAL = 1.0
#: Opacities are clamped to [EPS, 1 - EPS] where their log or log(1 - o) is taken.
OPACITY_EPS = 1e-6
#: The edge of the Bayer dither tile (64 threshold levels: budgets down to 1/64 of a view's
#: pixels stay spread evenly).
DITHER_TILE = 8
#: The window (pixels, odd) over which ``local_fraction`` counts the kept Gaussians around one:
#: a little more than a dither tile.
LOCAL_WINDOW = 9


@dataclass(frozen=True)
class GaussianBudget:
    """Keep ``keep`` Gaussians per target view: a count (an int >= 1) or a fraction in (0, 1]
    of them (``budget_count``), ranked by ``rank_by``: ``"learned"`` (the importance head,
    the kept Gaussians adapted to the budget), ``"dither"`` (what the untrained head does),
    ``"footprint"`` (opacity x screen area for the target camera), ``"opacity"`` or
    ``"random"`` (seeded with ``seed``), the controls; ``None``: learned where
    the model has the head, else dither (with a warning). ``tau`` > 0: the relaxed mask of
    training instead of the hard top-K. ``UniqueSplat.forward(budget=...)`` takes it.

    Examples:
        >>> GaussianBudget(0.3, rank_by="opacity")
        GaussianBudget(keep=0.3, rank_by='opacity', tau=None, seed=0)
        >>> GaussianBudget(0.0)
        Traceback (most recent call last):
        ...
        ValueError: budget must be a fraction in (0, 1] (or a count, an int >= 1), got 0.0
    """

    keep: float | int
    rank_by: str | None = None
    tau: float | None = None
    seed: int = 0

    def __post_init__(self):
        budget_count(self.keep, 1)  # the value's own checks, before any network runs
        if self.rank_by is not None and self.rank_by not in RANKINGS:
            raise ValueError(f"rank_by must be one of {RANKINGS} or None, got "
                             f"{self.rank_by!r}")

    @staticmethod
    def of(keep, rank_by: str | None = None, tau: float | None = None,
           seed: int = 0) -> "GaussianBudget | None":
        """The budget of these loose settings, ``None`` when ``keep`` is (every Gaussian)."""
        return None if keep is None else GaussianBudget(keep, rank_by, tau, seed)


def budget_count(budget, total: int) -> int:
    """K, the Gaussians a budget keeps of ``total``: an int is a count (>= 1; one at least
    ``total`` keeps them all), a float a fraction in (0, 1] (K = round(fraction x total),
    at least 1). Anything else is a ``ValueError`` naming ``budget``.

    Examples:
        >>> budget_count(100, 8192), budget_count(0.3, 8192), budget_count(10**6, 8192)
        (100, 2458, 8192)
        >>> budget_count(1.0, 8192), budget_count(1e-9, 8192)
        (8192, 1)
    """
    if isinstance(budget, bool) or not isinstance(budget, numbers.Real):
        raise ValueError(f"budget must be a count (an int >= 1) or a fraction in (0, 1], got "
                         f"{budget!r}")
    if isinstance(budget, numbers.Integral):
        if budget < 1:
            raise ValueError(f"budget must be a count >= 1 or a fraction in (0, 1], got "
                             f"{budget}")
        return min(int(budget), total)
    if not 0 < budget <= 1:  # also NaN
        raise ValueError(f"budget must be a fraction in (0, 1] (or a count, an int >= 1), "
                         f"got {budget}")
    return max(1, min(total, round(float(budget) * total)))


def top_k(scores: Float[Tensor, "s g"], k: int
          ) -> tuple[Int[Tensor, "s k"], Int[Tensor, "s k"]]:
    """The indices of the ``k`` highest scores of each row, ascending, and each one's rank
    (0: the highest). Ties go to the lower index (a stable descending sort)."""
    order = torch.sort(scores, dim=1, descending=True, stable=True).indices[:, :k]
    index, rank = order.sort(dim=1)  # rank[i, j]: where index[i, j] stood in ``order``
    return index, rank


def ranks(scores: Float[Tensor, "s g"]) -> Int[Tensor, "s g"]:
    """Each score's rank in its row (0: the highest; ties: the lower index first)."""
    order = torch.sort(scores, dim=1, descending=True, stable=True).indices
    arange = torch.arange(scores.shape[1], device=scores.device).expand_as(order)
    return torch.empty_like(order).scatter_(1, order, arange.contiguous())


def soft_mask(scores: Float[Tensor, "s g"], k: int, tau: float) -> Float[Tensor, "s g"]:
    """The relaxed top-``k`` mask of training: its value is 1 on the top ``k`` (as the hard
    selection keeps them) and ``sigmoid((scores - t) / tau)`` (< 1/2) on the rest, t midway
    between each row's k-th and (k+1)-th highest score; its gradient is that sigmoid's
    everywhere (on the kept ones a straight-through estimator's), with t moving with the
    scores as a budget of K requires: dt/ds_j = sigma'_j / sum sigma' (the threshold where the
    sigmoids sum to K, differentiated implicitly), so the gradient of the mask's sum is 0. A
    gradient can then only trade one Gaussian for another, never raise them all (with t
    fixed, "more opacity here" is true almost everywhere and every score drifts up). All ones
    when ``k`` keeps the whole row."""
    if k >= scores.shape[1]:
        return torch.ones_like(scores)
    top = scores.detach().topk(k + 1, dim=1).values  # descending
    t = 0.5 * (top[:, k - 1] + top[:, k])[:, None]
    slope = torch.sigmoid((scores.detach() - t) / tau)
    slope = slope * (1 - slope)  # sigma' (tau times it), detached
    weights = slope / slope.sum(1, keepdim=True).clamp(min=1e-30)
    moved = (weights * (scores - scores.detach())).sum(1, keepdim=True)  # 0, with t's gradient
    soft = torch.sigmoid((scores - t - moved) / tau)
    index, _ = top_k(scores.detach(), k)
    value = soft.detach().scatter(1, index, 1.0)  # the hard top-K's 1, the rest soft
    return value + (soft - soft.detach())  # (exactly ``value``: the second term is 0)


def bayer(n: int) -> Tensor:
    """The n x n Bayer index matrix (n a power of 2): 0 .. n^2 - 1, each 2x2 block of the
    recursion spreading its four ranks diagonally (ordered dithering).

    Examples:
        >>> bayer(2).tolist()
        [[0, 2], [3, 1]]
    """
    m = torch.zeros(1, 1, dtype=torch.long)
    while m.shape[0] < n:
        m = torch.cat([torch.cat([4 * m, 4 * m + 2], 1), torch.cat([4 * m + 3, 4 * m + 1], 1)])
    return m


def dither_offsets(views: int, h: int, w: int, gaussians_per_pixel: int = 1,
                   device: torch.device | str = "cpu") -> Float[Tensor, " g"]:
    """``-log T`` per Gaussian, in the Gaussians' order (view, pixel in raster order, Gaussian of
    the pixel): T = (index + 0.5) / levels from the ``DITHER_TILE`` Bayer matrix tiled over
    each view, the pixel's Gaussians at consecutive levels. All > 0; the same for every view."""
    b = bayer(DITHER_TILE)
    ys, xs = torch.arange(h) % DITHER_TILE, torch.arange(w) % DITHER_TILE
    index = b[ys[:, None], xs[None, :]].reshape(h * w, 1) * gaussians_per_pixel
    index = index + torch.arange(gaussians_per_pixel)  # [H*W, gpp]
    t = (index.double() + 0.5) / (DITHER_TILE**2 * gaussians_per_pixel)
    return (-t.log()).float().reshape(-1).repeat(views).to(device)


def local_fraction(kept: Bool[Tensor, "s g"], layout: tuple[int, int, int, int]
                   ) -> Float[Tensor, "s g"]:
    """The fraction of Gaussians kept in the ``LOCAL_WINDOW`` x ``LOCAL_WINDOW`` pixels around
    each (its own context view's image; the window clipped at the image's border), from the
    top-K mask ``kept``; ``layout`` = (views, H, W, Gaussians per pixel) of the G Gaussians."""
    s, g = kept.shape
    v, h, w, gpp = layout
    assert g == v * h * w * gpp, (g, layout)
    m = kept.float().view(s * v, h, w, gpp).mean(-1)[:, None]  # [S V, 1, H, W]
    f = F.avg_pool2d(m, LOCAL_WINDOW, stride=1, padding=LOCAL_WINDOW // 2,
                     count_include_pad=False)
    return f.view(s, v, h * w, 1).expand(s, v, h * w, gpp).reshape(s, g)


def adapt(gaussians: Gaussians, log_copies: Float[Tensor, "s k"],
          log_scale: Float[Tensor, "s k"]) -> Gaussians:
    """Gaussians with opacity 1 - (1 - o)^(e^a) (the coverage of e^a copies) and scales
    times e^s; a = s = 0 returns the same numbers (see the module docstring)."""
    o = gaussians.opacities
    copies_minus_one = torch.expm1(log_copies)  # e^a - 1, exactly 0 at a = 0
    more = -torch.expm1(copies_minus_one * torch.log1p(-o.clamp(max=1 - OPACITY_EPS)))
    factor = torch.exp(log_scale)
    return Gaussians(means=gaussians.means,
                     covariances=gaussians.covariances * factor.square()[..., None, None],
                     harmonics=gaussians.harmonics, opacities=o + (1 - o) * more,
                     scales=gaussians.scales * factor[..., None], rotations=gaussians.rotations)


def coverage_rule(log_local: Float[Tensor, "s k"]
                  ) -> tuple[Float[Tensor, "s k"], Float[Tensor, "s k"]]:
    """``(log_copies, log_scale) = (-log f, -log(f) / 2)`` for the kept fraction f around a
    Gaussian (``log_local`` <= 0), clamped to the bounds: the adaptation's start."""
    return ((-log_local).clamp(-MAX_LOG_COPIES, MAX_LOG_COPIES),
            (-0.5 * log_local).clamp(-MAX_LOG_SCALE, MAX_LOG_SCALE))


class ImportanceHead(nn.Module):
    """Per Gaussian, a log-density logit and ``ADAPT_FEATURES`` features from the Gaussian
    head's input (a 3x3 convolution, GELU, a 3x3 convolution to ``gpp (1 + F)`` channels, like
    the predictor's heads), and the adaptation MLP (``adapt_mlp``). Both last layers start at
    zero: the untrained head ranks and adapts as ``rank_by="dither"`` does."""

    def __init__(self, in_channels: int, hidden: int, gaussians_per_pixel: int):
        super().__init__()
        self.gpp = gaussians_per_pixel
        self.conv = nn.Sequential(
            nn.Conv2d(in_channels, hidden, 3, padding=1), nn.GELU(),
            nn.Conv2d(hidden, gaussians_per_pixel * (1 + ADAPT_FEATURES), 3, padding=1))
        self.adapt_mlp = nn.Sequential(nn.Linear(2 + ADAPT_FEATURES, hidden), nn.GELU(),
                                       nn.Linear(hidden, 2))
        for last in (self.conv[-1], self.adapt_mlp[-1]):
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)

    def forward(self, head_input: Float[Tensor, "vb c h w"], v: int, b: int
                ) -> tuple[Float[Tensor, "b g"], Float[Tensor, "b g f"]]:
        """Logits [B, G] and features [B, G, F] in the Gaussians' order (view-major, pixel in
        raster order, Gaussian of the pixel), from the head input in (v b) order."""
        out = self.conv(head_input).float()  # [(v b), gpp (1 + F), H, W]
        hw = out.shape[-2] * out.shape[-1]
        out = out.reshape(v, b, 1 + ADAPT_FEATURES, self.gpp, hw)
        out = out.permute(1, 0, 4, 3, 2).reshape(b, v * hw * self.gpp, 1 + ADAPT_FEATURES)
        return out[..., 0], out[..., 1:]

    def adaptation(self, log_fraction: float, log_local: Float[Tensor, "s k"],
                   features: Float[Tensor, "s k f"]
                   ) -> tuple[Float[Tensor, "s k"], Float[Tensor, "s k"]]:
        """``(log_copies, log_scale)`` per kept Gaussian from the budget's log K/G, the log of
        the kept fraction f around each (``log_local``, <= 0) and its features: the coverage
        rule ``(-log f, -log(f) / 2)`` plus the MLP's residual (bounded by tanh, 0 at the
        start), clamped to the bounds."""
        x = torch.cat([torch.full_like(log_local, log_fraction)[..., None],
                       log_local[..., None], features], -1)
        raw = MAX_RESIDUAL * torch.tanh(self.adapt_mlp(x) / MAX_RESIDUAL)
        return ((raw[..., 0] - log_local).clamp(-MAX_LOG_COPIES, MAX_LOG_COPIES),
                (raw[..., 1] - 0.5 * log_local).clamp(-MAX_LOG_SCALE, MAX_LOG_SCALE))


@dataclass
class Budgeted:
    """What ``apply_budget`` returns: the ``gaussians`` (K per set, or all G with a relaxed
    mask folded into their opacities), ``kept`` K, and for ``aux``: ``scores`` [S, G] (the
    ranking), ``kept_mask`` [S, G] (the hard top-K, also when relaxed) and ``mask`` [S, G]
    (the relaxed mask; ``None`` for the hard selection)."""

    gaussians: Gaussians
    kept: int
    scores: Tensor | None = None
    kept_mask: Tensor | None = None
    mask: Tensor | None = None


def take(t: Tensor, index: Tensor) -> Tensor:
    """``t[s, index[s, j], ...]``: the rows of each set that ``index`` [S, K] names."""
    rows = torch.arange(t.shape[0], device=t.device)[:, None]
    return t[rows, index]


def log_density(opacities: Float[Tensor, "s g"], logits: Float[Tensor, "s g"] | None
                ) -> Float[Tensor, "s g"]:
    """The log-density ``log o + r`` (o detached and clamped to >= OPACITY_EPS; r the head's
    logits, none for ``"dither"``)."""
    log_o = torch.log(opacities.detach().clamp(min=OPACITY_EPS))
    return log_o if logits is None else log_o + logits


def ranking_scores(rank_by: str, opacities: Float[Tensor, "s g"],
                   logits: Float[Tensor, "s g"] | None = None,
                   dither: Float[Tensor, " g"] | None = None, seed: int = 0,
                   footprint: Float[Tensor, "s g"] | None = None) -> Float[Tensor, "s g"]:
    """The scores ``rank_by`` ranks by: the opacity, the ``footprint`` scores given
    (``render.prune.footprint_scores``), uniform noise from a generator seeded with ``seed``
    (drawn on the CPU: the same selection on every device), or the log-density (with the
    head's ``logits`` for ``"learned"``) plus the ``dither`` offsets (``dither_offsets``)."""
    if rank_by == "opacity":
        return opacities.detach()
    if rank_by == "footprint":
        if footprint is None:
            raise ValueError("rank_by='footprint' needs the footprint scores of the target "
                             "cameras (render.prune.footprint_scores)")
        return footprint.detach()
    if rank_by == "random":
        g = torch.Generator().manual_seed(seed)
        return torch.rand(opacities.shape, generator=g).to(opacities.device)
    if dither is None or (rank_by == "learned" and logits is None):
        raise ValueError(f"rank_by={rank_by!r} needs the dither offsets"
                         + (" and the importance head's logits" if rank_by == "learned" else ""))
    return log_density(opacities, logits) + dither


def apply_budget(gaussians: Gaussians, budget, rank_by: str = "opacity",
                 logits: Float[Tensor, "s g"] | None = None,
                 features: Float[Tensor, "s g f"] | None = None,
                 head: ImportanceHead | None = None, dither: Float[Tensor, " g"] | None = None,
                 layout: tuple[int, int, int, int] | None = None, tau: float | None = None,
                 seed: int = 0, footprint: Float[Tensor, "s g"] | None = None) -> Budgeted:
    """Keep ``budget`` (``budget_count``) of each set's Gaussians by ``rank_by`` (one of
    ``RANKINGS``; ``"dither"`` needs the ``dither`` offsets and the Gaussians' ``layout``
    (views, H, W, Gaussians per pixel), ``"learned"`` also the head's ``logits`` and
    ``features`` and the ``head`` for the adaptation, ``"footprint"`` its scores per set).
    ``tau``: ``None`` for the hard top-K (K Gaussians per set), > 0 for the relaxed mask (all
    G, for training). See the module docstring.

    Examples:
        >>> g = Gaussians(means=torch.zeros(1, 4, 3), covariances=torch.eye(3).repeat(1, 4, 1, 1),
        ...               harmonics=torch.zeros(1, 4, 3, 1),
        ...               opacities=torch.tensor([[0.25, 0.75, 0.5, 0.75]]),
        ...               scales=torch.ones(1, 4, 3), rotations=torch.zeros(1, 4, 4))
        >>> out = apply_budget(g, 0.5, "opacity")
        >>> out.kept, out.gaussians.opacities.tolist(), out.kept_mask.tolist()
        (2, [[0.75, 0.75]], [[False, True, False, True]])
    """
    if rank_by not in RANKINGS:
        raise ValueError(f"rank_by must be one of {RANKINGS}, got {rank_by!r}")
    if tau is not None and not (isinstance(tau, (int, float)) and tau > 0):
        raise ValueError(f"budget_tau must be None (the hard top-K) or > 0, got {tau!r}")
    g = gaussians.opacities.shape[1]
    k = budget_count(budget, g)
    if k >= g:  # everything kept: the unbudgeted Gaussians themselves
        return Budgeted(gaussians, g)
    learned = rank_by == "learned"
    if learned and (features is None or head is None or logits is None):
        raise ValueError("rank_by='learned' needs the importance head, its logits and features")
    scores = ranking_scores(rank_by, gaussians.opacities, logits, dither, seed, footprint)
    adapted = rank_by in ("learned", "dither")
    if adapted and layout is None:
        raise ValueError(f"rank_by={rank_by!r} needs the Gaussians' layout")
    log_fraction = math.log(k / g)
    kept_mask = ranks(scores.detach()) < k  # the hard top-K
    log_local = None
    if adapted:  # the kept fraction around each Gaussian, in log (a kept one counts itself)
        log_local = local_fraction(kept_mask, layout).clamp(min=1 / LOCAL_WINDOW**2).log()

    def adaptation(log_local_kept, features_kept):
        if learned:
            return head.adaptation(log_fraction, log_local_kept, features_kept)
        return coverage_rule(log_local_kept)

    if tau is None:  # the hard top-K
        index, _ = top_k(scores.detach(), k)
        kept = Gaussians(**{name: take(getattr(gaussians, name), index)
                            for name in ("means", "covariances", "harmonics", "opacities",
                                         "scales", "rotations")})
        if adapted:
            kept = adapt(kept, *adaptation(take(log_local, index),
                                           take(features, index) if learned else None))
        return Budgeted(kept, k, scores, kept_mask)
    mask = soft_mask(scores, k, tau)
    out = gaussians
    if adapted:  # the kept ones adapted as at inference; the dropped ones only fade
        a, s_ = adaptation(log_local, features)
        out = adapt(out, a * kept_mask, s_ * kept_mask)
    out = Gaussians(means=out.means, covariances=out.covariances, harmonics=out.harmonics,
                    opacities=out.opacities * mask, scales=out.scales, rotations=out.rotations)
    return Budgeted(out, k, scores, kept_mask, mask)
