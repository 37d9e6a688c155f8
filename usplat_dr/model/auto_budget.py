"""An automatic Gaussian count: per scene, the smallest budget whose loss against all of the
model's Gaussians is predicted, without the target images, to stay within a tolerance.

``UniqueSplat.forward(..., budget=AutoBudget())`` (``usplat eval|render|export-ply
--gaussians auto``, ``predict(..., budget="auto")``) does, per scene:

1. **The proxy.** The context views are rendered from the scene's own Gaussians (the context
   cameras as targets), with all of them and with the budgets of ``AUTO_KEEPS`` from the
   largest down, ranked as the budget would rank them; the proxy loss at a budget is
   PSNR(all) - PSNR(K), each against the context view's own image, in dB.
2. **The prediction.** A context view sees each Gaussian it put on its own pixels, so it
   overstates what a target loses (about 8x near 50% on the held-out synthetic set). A
   ``Calibration`` made on scenes that are not evaluated (a development set) maps it, per
   budget, to the target's loss: a least-squares line in the proxy loss plus a margin, a high
   quantile of the line's residuals there. Without one (a model nobody calibrated) the proxy
   loss itself is the prediction, which overstates and so keeps more.
3. **The count.** The smallest budget whose loss, and every larger budget's, is predicted
   within ``tolerance`` (default 0.2 dB): the renders go down from the largest and stop at the
   first that fails; every Gaussian where the largest fails. Against the smallest budget
   predicted within it wherever it lies (the rule the calibration study read first), this
   never keeps less; on the development set it chose the same at 0.5 and 1 dB and kept 99.3%
   against 98.0% at 0.2 dB, with 1-3 renders a scene instead of 7-8 (on the held-out set: the
   same choices).
4. **Merging.** With ``merge=True`` (the default) the kept Gaussians are rendered with
   ``PruneSettings(merge=True)`` (render/prune.py): near-duplicates that fall on one target
   pixel, depth and colour bin, the two context views' copies of a surface above all, become
   one moment-matched Gaussian, so a duplicated surface is modelled once.

The chosen fraction is ``out.aux["auto_keep"]`` [B], the proxy readings
``out.aux["auto_readings"]`` (per scene, ``{keep: (proxy loss, predicted loss)}`` for the
budgets rendered), the Gaussians each target kept ``out.aux["kept"]`` and rendered after the
merge ``out.aux["rendered"]``. The calibrations of the shipped models are in their manifest
entries (``auto_budget``); train/studies/auto_budget_proxy.py makes one for any checkpoint and
development set (``--ship``), and measures what the count keeps and loses on held-out scenes
(train/studies/LOG.md, "An automatic count").
"""

import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass

import torch

from usplat_dr.model.budget import RANKINGS, GaussianBudget

#: The budgets the count chooses from (fractions of the Gaussians, ascending); 1 beyond them.
AUTO_KEEPS = (0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.7)
#: The default tolerance: the loss against all Gaussians the count may predict, in dB.
DEFAULT_TOLERANCE_DB = 0.2


#: The most budgets one calibration may hold a line for (it measures ``AUTO_KEEPS``).
MAX_FITS = 64


@dataclass(frozen=True)
class Calibration:
    """The proxy loss mapped to the target's loss, per budget: ``fits`` holds (keep,
    intercept, slope, margin) rows; the predicted loss at ``keep`` is intercept + slope x
    proxy + margin. ``rank_by``: the ranking it was measured with; ``quantile``: the residual
    quantile the margins are; ``data``: the development set it was fitted on; ``size``: the
    shorter side of the images it was measured at (``None``: not recorded), where a render of
    another size is warned about.

    Examples:
        >>> c = Calibration("dither", ((0.5, 0.1, 0.5, 0.2),), 0.9, "dev")
        >>> round(c.predicted(0.5, 1.0), 6), c.predicted(0.3, 1.0)
        (0.8, None)
    """

    rank_by: str
    fits: tuple[tuple[float, float, float, float], ...]
    quantile: float
    data: str
    size: int | None = None

    def __post_init__(self):
        if self.rank_by not in RANKINGS:
            raise ValueError(f"Calibration.rank_by must be one of {RANKINGS}, got "
                             f"{self.rank_by!r}")
        if not self.fits:
            raise ValueError("Calibration.fits must hold at least one (keep, intercept, slope, "
                             "margin) row")
        if len(self.fits) > MAX_FITS:
            raise ValueError(f"Calibration.fits holds {len(self.fits)} rows, more than the "
                             f"{MAX_FITS} budgets a calibration measures")
        for row in self.fits:
            if len(row) != 4 or not all(isinstance(x, numbers.Real) and math.isfinite(x)
                                        for x in row) or not 0 < row[0] < 1:
                raise ValueError(f"Calibration.fits rows must be (keep in (0, 1), intercept, "
                                 f"slope, margin), finite numbers, got {row!r}")
        keeps = [row[0] for row in self.fits]
        if len(set(keeps)) != len(keeps):
            raise ValueError(f"Calibration.fits has two rows for one budget: {keeps}")
        if not (isinstance(self.quantile, numbers.Real) and 0 < self.quantile < 1):
            raise ValueError(f"Calibration.quantile must be in (0, 1), got {self.quantile!r}")
        if self.size is not None and not (isinstance(self.size, int)
                                          and 1 <= self.size <= 65_536):
            raise ValueError(f"Calibration.size must be pixels in 1..65,536, got {self.size!r}")

    def predicted(self, keep: float, proxy_db: float) -> float | None:
        """The target's loss predicted at ``keep`` from the proxy loss; ``None`` where this
        calibration has no line for that budget."""
        for k, a, b, margin in self.fits:
            if abs(k - keep) < 1e-9:
                return a + b * proxy_db + margin
        return None

    def as_dict(self) -> dict:
        return {"rank_by": self.rank_by, "quantile": self.quantile, "data": self.data,
                "size": self.size, "fits": [list(row) for row in self.fits]}

    @staticmethod
    def from_dict(d: dict, where: str = "calibration") -> "Calibration":
        """The calibration a manifest entry or checkpoint records (``as_dict``'s form); a
        malformed one is a ``ValueError`` naming ``where``."""
        try:
            size = d.get("size")
            return Calibration(str(d["rank_by"]), tuple(tuple(float(x) for x in row)
                                                        for row in d["fits"]),
                               float(d["quantile"]), str(d.get("data", "")),
                               None if size is None else int(size))
        except (AttributeError, KeyError, TypeError, ValueError, OverflowError) as e:
            raise ValueError(f"{where}: not an automatic count's calibration ({{'rank_by', "
                             f"'quantile', 'data', 'fits': [[keep, intercept, slope, margin], "
                             f"...]}}): {e}") from e

    @staticmethod
    def fit(per_scene: dict, quantile: float, rank_by: str, data: str,
            size: int | None = None) -> "Calibration":
        """Fitted on ``per_scene`` ({scene: {keep: (proxy loss, target loss)}}, a development
        set's): per budget below 1, the least-squares line of the target loss in the proxy
        loss and the ``quantile`` of its residuals (target - line) as the margin."""
        if not 0.0 < quantile < 1.0:
            raise ValueError(f"quantile must be between 0 and 1, got {quantile!r}")
        keeps = sorted({k for found in per_scene.values() for k in found if k < 1.0})
        rows = []
        for keep in keeps:
            pairs = [found[keep] for found in per_scene.values() if keep in found]
            if len(pairs) < 3:
                raise ValueError(f"calibration: budget {keep:g} has {len(pairs)} scenes; a "
                                 f"line and its residuals need at least 3")
            xs = torch.tensor([p[0] for p in pairs], dtype=torch.float64)
            ys = torch.tensor([p[1] for p in pairs], dtype=torch.float64)
            design = torch.stack([torch.ones_like(xs), xs], dim=1)
            coef = torch.linalg.lstsq(design, ys[:, None]).solution[:, 0]
            residual = ys - design @ coef
            rows.append((float(keep), float(coef[0]), float(coef[1]),
                         float(torch.quantile(residual, quantile))))
        return Calibration(rank_by, tuple(rows), quantile, data, size)


@dataclass(frozen=True)
class AutoBudget:
    """Choose each scene's Gaussian budget (see the module's docstring): the smallest of
    ``keeps`` whose loss is predicted within ``tolerance`` dB, ranked by ``rank_by`` (``None``:
    dither, which on the development set let the count keep less than the learned ranking,
    98% against 100% of the Gaussians at 0.2 dB and 78% against 96% at 0.5: the learned one
    loses more at the 50-70% a count mostly keeps), predicted through
    ``calibration`` (``None``: the model's own, ``model.auto_calibration``, else the proxy
    uncalibrated); ``merge``: render the kept Gaussians with near-duplicates merged.

    Examples:
        >>> AutoBudget().tolerance
        0.2
        >>> AutoBudget(tolerance=-1)
        Traceback (most recent call last):
        ...
        ValueError: AutoBudget.tolerance must be a number of dB >= 0 (0.2 by default), got -1
    """

    tolerance: float | int = DEFAULT_TOLERANCE_DB
    rank_by: str | None = None
    merge: bool = True
    calibration: Calibration | None = None
    keeps: tuple[float, ...] = AUTO_KEEPS

    def __post_init__(self):
        if (not isinstance(self.tolerance, numbers.Real) or isinstance(self.tolerance, bool)
                or not math.isfinite(self.tolerance) or self.tolerance < 0):
            raise ValueError(f"AutoBudget.tolerance must be a number of dB >= 0 "
                             f"({DEFAULT_TOLERANCE_DB} by default), got {self.tolerance!r}")
        if self.rank_by is not None and self.rank_by not in RANKINGS:
            raise ValueError(f"AutoBudget.rank_by must be one of {RANKINGS} or None, got "
                             f"{self.rank_by!r}")
        if (not self.keeps or list(self.keeps) != sorted(set(self.keeps))
                or not all(0 < k < 1 for k in self.keeps)):
            raise ValueError(f"AutoBudget.keeps must be ascending distinct fractions in (0, 1), "
                             f"got {self.keeps!r}")


def make_budget(keep, rank_by: str | None = None,
                tolerance: float | None = None) -> "GaussianBudget | AutoBudget | None":
    """The budget of the loose settings commands and ``predict`` take: ``None`` (every
    Gaussian), ``"auto"`` (an ``AutoBudget`` with ``tolerance``, default 0.2 dB), an
    ``AutoBudget`` or ``GaussianBudget`` as it is, or a count / fraction.

    Examples:
        >>> make_budget("auto", tolerance=0.5).tolerance, make_budget(0.3).keep
        (0.5, 0.3)
    """
    if isinstance(keep, (AutoBudget, GaussianBudget)):
        return keep
    if isinstance(keep, str):
        if keep != "auto":
            raise ValueError(f"budget must be a count, a fraction, 'auto' or None, got "
                             f"{keep!r}")
        return AutoBudget(DEFAULT_TOLERANCE_DB if tolerance is None else tolerance, rank_by)
    if tolerance is not None and keep is not None:
        raise ValueError(f"a tolerance ({tolerance}) applies to budget='auto' only, got "
                         f"budget={keep!r}")
    return GaussianBudget.of(keep, rank_by)


def image_psnr(pred: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """-10 log10(MSE) per image [..., 3, H, W], both clipped to [0, 1]: the protocol's PSNR
    (``evaluation.metrics.psnr``, which this layer may not import; tested equal)."""
    mse = ((pred.clamp(0, 1) - reference.clamp(0, 1)) ** 2).mean(dim=(-3, -2, -1))
    return -10 * torch.log10(mse)


def choose_keep(proxy_loss: Callable[[float], float], auto: AutoBudget,
                calibration: Calibration | None) -> tuple[float, dict]:
    """The smallest of ``auto.keeps`` whose predicted loss, and every larger one's, is within
    ``auto.tolerance`` (1.0 where the largest's is not), and the readings ``{keep: (proxy loss,
    predicted loss)}`` of the budgets tried. ``proxy_loss(keep)`` renders and measures one
    budget; it is called from the largest budget down and not past the first that fails. A
    budget the calibration has no line for is predicted by its proxy loss.

    Examples:
        >>> losses = {0.05: 0.0, 0.1: 1.0, 0.15: 0.1, 0.2: 0.0}
        >>> choose_keep(losses.get, AutoBudget(keeps=(0.05, 0.1, 0.15, 0.2)), None)[0]
        0.15
    """
    readings, chosen = {}, 1.0
    for keep in reversed(auto.keeps):
        proxy = float(proxy_loss(keep))
        predicted = None if calibration is None else calibration.predicted(keep, proxy)
        predicted = proxy if predicted is None else predicted
        readings[keep] = (proxy, predicted)
        if not predicted <= auto.tolerance:  # NaN (a reading that failed) stops it too
            break
        chosen = keep
    return chosen, readings
