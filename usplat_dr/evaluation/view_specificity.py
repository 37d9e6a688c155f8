"""The view-specificity meter: does a UniqueSplat (c)'s Delta W vary with the target view, and
does the variation change the renders?

A (c) predicts W + Delta W per target view. If Delta W is the same for every target of a scene,
the model is (b) plus a scene-dependent constant, and a verdict on "(c)" tests the training
protocol, not per-view weights. The meter reads, per scene:

- ``spread[layer]``: how much Delta W differs between the scene's targets,
  sqrt(mean_n ||Delta W_n - mean_m Delta W_m||^2) / ||W||, weight and bias together (the
  layer's flat parameter vector, as H_a outputs it);
- ``size[layer]``: the size of the scene's mean Delta W, ||mean_n Delta W_n|| / ||W||;
- ``d_mean`` / ``d_mean_abs``: PSNR(per-target Delta W) - PSNR(the scene's mean Delta W for
  every target), the mean over the scene's targets of the difference and of its absolute
  value: what the view dependence does to the renders (0 when Delta W is constant across
  targets, and its sign says whether it helps);
- ``d_zero`` / ``d_zero_abs``: the same against Delta W = 0 (what the branch does at all).

All three renders go through the same code (a full Delta W per target, ``forward(hooks=...)``
on one encoding), so the differences come from Delta W alone. ``summarise`` gives means over
scenes with Student's t 95% intervals over scenes.

Examples:
    >>> import torch
    >>> from usplat_dr.model.hypernet.hypernetwork import LayerDelta
    >>> d = LayerDelta(bias=torch.zeros(2, 3), full=torch.zeros(2, 3, 4, 1, 1))
    >>> d.full[1] += 1.0  # two targets of one scene: 0 and 1 everywhere
    >>> spread, size = layer_spread(d, (torch.ones(3, 4, 1, 1), torch.zeros(3)), 1, 2)
    >>> round(spread.item(), 6), round(size.item(), 6)  # half the difference, half the mean
    (0.5, 0.5)
"""

import csv
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from usplat_dr.data.types import model_inputs
from usplat_dr.evaluation.metrics import psnr
from usplat_dr.evaluation.verdict import t_interval
from usplat_dr.model.hypernet.hypernetwork import LayerDelta
from usplat_dr.model.uniquesplat import StudyHooks

#: The manipulation check's bound (dB): a (c) counts as view-specific ("live") when the mean
#: over held-out scenes of the mean absolute PSNR(per-target Delta W) - PSNR(scene-mean Delta W)
#: is at least this. Fixed before the verdict's re-run: a twentieth of the paper's (c) - (b) of
#: 0.58 dB would still be below it, while the shipped (c) reads 0.0000 dB.
LIVE_BOUND_DB = 0.05


def full_delta(d: LayerDelta) -> LayerDelta:
    """``d`` as a full Delta W per target (``full`` [T, O, I, k, k]; ``u`` @ ``v`` for the
    rank-r form, exact up to float32 rounding)."""
    if d.full is not None:
        return d
    if d.bias.ndim != 2:
        raise ValueError(f"the meter reads a bias change per target [T, O], got "
                         f"{list(d.bias.shape)} (a bias per context view has no full form)")
    full = torch.einsum("tor,trikl->toikl", d.u, d.v)
    return LayerDelta(bias=d.bias, full=full)


def _flat(d: LayerDelta) -> Tensor:
    """[T, P]: each target's Delta W, weight then bias."""
    d = full_delta(d)
    return torch.cat((d.full.flatten(1), d.bias.flatten(1)), 1)


def layer_spread(delta: LayerDelta, weight: tuple[Tensor, Tensor], b: int, n: int
                 ) -> tuple[Tensor, Tensor]:
    """Per scene [B]: the spread of Delta W across its ``n`` targets and the size of its mean
    Delta W, both relative to ||W|| (``weight``: (weight, bias); module docstring)."""
    flat = _flat(delta).double().view(b, n, -1)  # [B, N, P]
    norm_w = torch.cat((weight[0].flatten(), weight[1].flatten())).double().norm()
    mean = flat.mean(1, keepdim=True)
    spread = (flat - mean).square().sum(-1).mean(1).sqrt() / norm_w
    return spread.float(), (mean[:, 0].norm(dim=-1) / norm_w).float()


def scene_mean(delta: LayerDelta, b: int, n: int) -> LayerDelta:
    """Each target's Delta W replaced by its scene's mean over the ``n`` targets (full form)."""
    d = full_delta(delta)
    full = d.full.view(b, n, *d.full.shape[1:]).mean(1, keepdim=True).expand(
        b, n, *d.full.shape[1:]).reshape(d.full.shape)
    bias = d.bias.view(b, n, -1).mean(1, keepdim=True).expand(b, n, -1).reshape(d.bias.shape)
    return LayerDelta(bias=bias, full=full)


@dataclass(frozen=True)
class SceneReading:
    """The meter on one scene (module docstring)."""

    scene: str
    targets: int
    spread: dict[str, float]
    size: dict[str, float]
    psnr: float  # mean PSNR over the targets with the model's own (per-target) Delta W
    d_mean: float
    d_mean_abs: float
    d_zero: float
    d_zero_abs: float

    def row(self) -> dict:
        """A flat row (CSV): ``spread_<layer>``, ``size_<layer>`` and the PSNR differences."""
        return {"scene": self.scene, "targets": self.targets,
                **{f"spread_{k}": v for k, v in self.spread.items()},
                **{f"size_{k}": v for k, v in self.size.items()},
                "psnr": self.psnr, "d_mean": self.d_mean, "d_mean_abs": self.d_mean_abs,
                "d_zero": self.d_zero, "d_zero_abs": self.d_zero_abs}


@torch.no_grad()
def read_batch(model, batch: dict, device: torch.device | str = "cpu",
               settings=None) -> list[SceneReading]:
    """The meter on each scene of ``batch`` (a collated batch of examples with >= 2 targets
    each) for ``model``, a UniqueSplat with a view-specific branch. The model is left in the
    mode it was in; its Delta W is computed as in evaluation (``model.eval()``)."""
    if getattr(model, "specific", None) is None:
        raise ValueError("model has no view-specific branch (variant 'full'): nothing to meter")
    inputs = model_inputs(batch, device)
    b, n = inputs.target_extrinsics.shape[:2]
    if n < 2:
        raise ValueError(f"the meter compares a scene's targets: batch needs >= 2 target views "
                         f"per scene, got {n}")
    was_training = model.training
    model.eval()
    try:
        with model._autocast(inputs.images.device):  # the precision forward would use
            encoding = model.encode(inputs.images, inputs.extrinsics, inputs.intrinsics,
                                    inputs.near, inputs.far)
            deltas = {k: full_delta(d) for k, d in model.view_delta_w(
                inputs.images, inputs.extrinsics, inputs.intrinsics,
                inputs.target_extrinsics, inputs.target_intrinsics, inputs.target_near,
                inputs.target_far, encoding=encoding).items()}
        deltas = {k: LayerDelta(bias=d.bias.float(), full=d.full.float())
                  for k, d in deltas.items()}
        weights = model.generated_weights()
        arms = {"own": deltas,
                "mean": {k: scene_mean(d, b, n) for k, d in deltas.items()},
                "zero": {k: LayerDelta(bias=torch.zeros_like(d.bias),
                                       full=torch.zeros_like(d.full))
                         for k, d in deltas.items()}}
        gt = batch["target"]["image"].to(device)
        scores = {}
        for arm, dw in arms.items():
            out = model(*inputs, hooks=StudyHooks(encoding=encoding, delta_w=dw),
                        settings=settings, prune=None)
            scores[arm] = psnr(out.color, gt).double().cpu()  # [B, N]
        spreads = {k: layer_spread(d, weights[k], b, n) for k, d in deltas.items()}
    finally:
        model.train(was_training)
    readings = []
    for i in range(b):
        dm = scores["own"][i] - scores["mean"][i]
        dz = scores["own"][i] - scores["zero"][i]
        readings.append(SceneReading(
            scene=str(batch["scene"][i]) if "scene" in batch else str(i), targets=n,
            spread={k: float(s[0][i]) for k, s in spreads.items()},
            size={k: float(s[1][i]) for k, s in spreads.items()},
            psnr=float(scores["own"][i].mean()), d_mean=float(dm.mean()),
            d_mean_abs=float(dm.abs().mean()), d_zero=float(dz.mean()),
            d_zero_abs=float(dz.abs().mean())))
    return readings


@dataclass(frozen=True)
class Summary:
    """The meter over a set of scenes: per layer the mean spread and size (relative to ||W||),
    and each PSNR difference's mean over scenes with its 95% t interval over scenes."""

    scenes: int
    spread: dict[str, float]
    size: dict[str, float]
    psnr: dict[str, tuple[float, float, float]] = field(default_factory=dict)

    @property
    def live(self) -> bool:
        """The manipulation check: mean |PSNR(per-target) - PSNR(scene mean)| >= the bound."""
        return self.psnr["d_mean_abs"][0] >= LIVE_BOUND_DB

    def as_dict(self) -> dict:
        return {"scenes": self.scenes, "spread_rel_w": self.spread, "size_rel_w": self.size,
                **{k: {"mean_db": m, "low": lo, "high": hi}
                   for k, (m, lo, hi) in self.psnr.items()},
                "live": self.live, "live_bound_db": LIVE_BOUND_DB}

    def line(self) -> str:
        """One line for logs and reports."""
        sp = max(self.spread.values())
        m, lo, hi = self.psnr["d_mean_abs"]
        z = self.psnr["d_zero"]
        return (f"view-specificity over {self.scenes} scenes: Delta W spread across targets "
                f"<= {sp:.2e} of ||W|| (largest layer); |PSNR(per-target) - PSNR(scene-mean "
                f"Delta W)| = {m:.4f} dB [{lo:.4f}, {hi:.4f}]; PSNR(per-target) - PSNR(Delta "
                f"W = 0) = {z[0]:+.4f} dB [{z[1]:+.4f}, {z[2]:+.4f}]; branch "
                f"{'live' if self.live else 'not live'} (bound {LIVE_BOUND_DB} dB)")


def manipulation_check(per_scene_csv, split: str = "standard") -> dict | None:
    """The meter's columns of an evaluation's ``per_scene.csv`` (``evaluate``'s, for a (c))
    on ``split``: ``scenes``, the mean ``view_psnr_abs`` with its t interval, the largest
    ``view_spread``, and ``live`` (the mean >= ``LIVE_BOUND_DB``); None where the file has no
    meter (a model without the view-specific branch)."""
    with open(per_scene_csv, newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["split"] == split and r.get("view_psnr_abs")]
    if not rows:
        return None
    vals = [float(r["view_psnr_abs"]) for r in rows]
    lo, hi = t_interval(vals)
    mean = float(np.mean(vals))
    return {"scenes": len(rows), "psnr_abs_db": mean, "low": lo, "high": hi,
            "spread_rel_w": max(float(r["view_spread"]) for r in rows),
            "live": mean >= LIVE_BOUND_DB}


def summarise(readings: list[SceneReading]) -> Summary:
    """Means over scenes of ``readings`` (``read_batch``'s), with t intervals."""
    if not readings:
        raise ValueError("readings is empty: the meter needs at least one scene")
    layers = list(readings[0].spread)
    psnrs = {}
    for key in ("d_mean", "d_mean_abs", "d_zero", "d_zero_abs"):
        vals = [getattr(r, key) for r in readings]
        psnrs[key] = (float(np.mean(vals)), *t_interval(vals))
    return Summary(scenes=len(readings),
                   spread={k: float(np.mean([r.spread[k] for r in readings])) for k in layers},
                   size={k: float(np.mean([r.size[k] for r in readings])) for k in layers},
                   psnr=psnrs)
