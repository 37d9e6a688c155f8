"""What a training stage trains (``train.trainable``: everything; the importance head of the
Gaussian-budget stage; the view-specific branch) and the Gaussian budget of each step
(``train.budget_fractions``)."""

import math
import random

import torch

from usplat_dr.config import ConfigError
from usplat_dr.model.budget import GaussianBudget
from usplat_dr.training.config import RootCfg


def freeze_for_budget(model: torch.nn.Module, c: RootCfg) -> None:
    """Check the budget settings (``train.budget_fractions``, ``train.trainable``) against the
    model (a ``ConfigError`` naming the key and the fix) and freeze what ``train.trainable``
    leaves out: for ``budget`` every parameter but the importance head's and the adaptation's,
    for ``view_specific`` every parameter but the view-specific branch's (E_H, the lateral
    convs, Proj, phi and H_s)."""
    tc = c.train
    head = getattr(model, "importance", None)
    if (tc.budget_fractions or tc.trainable == "budget") and head is None:
        raise ConfigError("train.budget_fractions and train.trainable=budget need a model "
                          "with an importance head: set model.overrides.importance=true (the "
                          "config synthetic_tiny_budget.yaml does)")
    if tc.trainable == "view_specific":
        if getattr(model, "specific", None) is None:
            raise ConfigError("train.trainable=view_specific trains the view-specific branch, "
                              "which this model lacks: set model.variant=full")
        for name, p in model.named_parameters():
            p.requires_grad_(name.split(".", 1)[0] in ("view_embedding", "specific"))
        return
    if tc.trainable != "budget":
        return
    if not tc.budget_fractions or (tc.budget_sampling == "choice"
                                   and all(f == 1 for f in tc.budget_fractions)):
        raise ConfigError("train.trainable=budget trains only the importance head, which a "
                          "step learns from only when its budget keeps fewer than all the "
                          "Gaussians: set train.budget_fractions below 1")
    if tc.budget_sampling == "choice" and 1.0 in tc.budget_fractions:
        raise ConfigError(f"train.budget_fractions={list(tc.budget_fractions)} holds 1 with "
                          f"train.trainable=budget: such a step keeps every Gaussian and "
                          f"leaves nothing to train (the loss has no gradient); drop it")
    for name, p in model.named_parameters():
        p.requires_grad_(name.split(".", 1)[0] == "importance")


def step_budget(c: RootCfg, step: int) -> GaussianBudget | None:
    """The ``GaussianBudget`` of step ``step`` (``None`` without ``train.budget_fractions``):
    ranked by the learned head, relaxed with the annealed ``tau``. Drawn from a generator
    seeded with the run's seed and the step: the same on every rank and after a resume, and no
    RNG state touched."""
    tc = c.train
    if not tc.budget_fractions:
        return None
    rng = random.Random(c.seed * 1_000_003 + step)
    if tc.budget_sampling == "choice":
        fraction = rng.choice(tc.budget_fractions)
    else:
        lo, hi = math.log(min(tc.budget_fractions)), math.log(max(tc.budget_fractions))
        fraction = math.exp(rng.uniform(lo, hi))
    t0, t1 = tc.budget_tau
    tau = t0 * (t1 / t0) ** min(step / max(tc.steps - 1, 1), 1.0)
    return GaussianBudget(float(fraction), rank_by="learned", tau=tau)
