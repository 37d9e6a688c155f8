"""The optimiser of training: Adam (fused where torch has it), its parameter groups (a
per-branch learning rate for the hypernetwork), and gradient clipping with the per-part norms
``metrics.csv`` logs."""

import math

import torch

from usplat_dr.config import ConfigError


def adam(params, lr: float) -> torch.optim.Adam:
    """Adam, fused where this torch has the fused kernel for the parameters' device (one
    kernel for all parameters: 31 -> 14 ms a step for the tiny preset's 1.7M parameters on
    one core; the same update up to float rounding). ``params``: tensors or param groups."""
    params = list(params)
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError):  # no fused kernel for this device or torch version
        return torch.optim.Adam(params, lr=lr)


# `float | int`, not `float`: beartype (pytest's run-time type checks) rejects an int for a float.
def parameter_groups(model: torch.nn.Module, lr: float | int,  # noqa: PYI041
                     hyper_lr_scale: float | int = 1.0) -> list[dict]:  # noqa: PYI041
    """Adam's parameter groups: the primary network at ``lr``; the hypernetwork branches
    (e_a and H_a, H_s, the view-specific features) and the importance head at
    ``lr * hyper_lr_scale`` (``optimizer.hyper_lr_scale``: the per-branch learning rate of
    docs/learning.md; 1 is the paper's single rate). One group when the scale is 1 or the
    model has no hypernetwork. Frozen parameters (``requires_grad`` off) are left out."""
    scale = float(hyper_lr_scale)
    if not (math.isfinite(scale) and scale > 0):
        raise ConfigError(f"optimizer.hyper_lr_scale must be a positive number, got "
                          f"{hyper_lr_scale!r}")
    primary, hyper = [], []
    for name, p in model.named_parameters():
        if p.requires_grad:  # (train.trainable=budget freezes the rest)
            (primary if name.split(".", 1)[0] == "primary" else hyper).append(p)
    if scale == 1.0 or not hyper:
        # model.parameters()'s order: Adam's state is keyed by position, so checkpoints of
        # runs before per-branch rates existed resume onto the same parameters
        return [{"params": [p for p in model.parameters() if p.requires_grad], "lr": lr}]
    groups = [{"params": primary, "lr": lr}, {"params": hyper, "lr": lr * scale}]
    return [g for g in groups if g["params"]]  # (frozen parameters are in neither)

def optimiser_and_schedule(model: torch.nn.Module, c, steps: int):
    """Adam over ``parameter_groups`` and its one-cycle cosine schedule over ``steps`` (+10)
    steps, from the ``optimizer`` section ``c`` (``lr``, ``hyper_lr_scale``,
    ``warm_up_fraction``)."""
    groups = parameter_groups(model, c.lr, c.hyper_lr_scale)
    optimizer = adam(groups, c.lr)
    scheduler = torch.optim.lr_scheduler.OneCycleLR(
        optimizer, [g["lr"] for g in groups], total_steps=steps + 10,
        pct_start=c.warm_up_fraction, cycle_momentum=False, anneal_strategy="cos")
    return optimizer, scheduler


#: Parameter groups whose gradient norms (before clipping) go into metrics.csv: the primary
#: network, the view-agnostic branch (e_a, H_a), the view-specific hypernetwork H_s, the
#: view-specific features (ResNet18, lateral convs, Proj, phi) and the importance head.
GRAD_GROUPS: dict[str, str] = {
    "primary": "grad_primary", "agnostic": "grad_agnostic",
    "specific": "grad_specific", "view_embedding": "grad_view_features",
    "importance": "grad_importance"}


def group_grad_norms(model: torch.nn.Module) -> dict:
    """Gradient norms per part of the network (``GRAD_GROUPS``), before clipping."""
    groups: dict[str, list[torch.Tensor]] = {}
    for name, p in model.named_parameters():
        key = GRAD_GROUPS.get(name.split(".", 1)[0])
        if key is not None and p.grad is not None:
            groups.setdefault(key, []).append(p.grad.detach())
    # One foreach kernel per group (a per-parameter float64 sum cost ~14 ms a step).
    norms = {k: torch.stack(torch._foreach_norm(g)).norm() for k, g in groups.items()}
    return dict(zip(norms, torch.stack(list(norms.values())).tolist())) if norms else {}


@torch.no_grad()
def clip_gradients(model: torch.nn.Module, max_norm: float) -> tuple[torch.Tensor, dict]:
    """Clip the gradients to a global norm of ``max_norm``; returns the norm before clipping
    and ``group_grad_norms(model)``. The same numbers as those two calls (``group_grad_norms``
    then ``torch.nn.utils.clip_grad_norm_``), from one pass over the per-parameter norms
    instead of two (~2 ms of a 64x64 tiny step at two threads)."""
    named = [(n, p.grad) for n, p in model.named_parameters() if p.grad is not None]
    grads = [g for _, g in named]
    if not grads or len({(g.device, g.dtype) for g in grads}) > 1:
        parts = group_grad_norms(model)  # torch's own grouping by device and dtype
        return torch.nn.utils.clip_grad_norm_(model.parameters(), max_norm), parts
    norms = torch._foreach_norm(grads)
    groups: dict[str, list[torch.Tensor]] = {}
    for (name, _), n in zip(named, norms):
        key = GRAD_GROUPS.get(name.split(".", 1)[0])
        if key is not None:
            groups.setdefault(key, []).append(n)
    group_norms = [torch.stack(v).norm() for v in groups.values()]
    parts = dict(zip(groups, torch.stack(group_norms).tolist())) if groups else {}
    # clip_grad_norm_'s arithmetic, step for step: the norm of the stacked norms, then
    # every gradient times min(1, max_norm / (norm + 1e-6))
    total = torch.linalg.vector_norm(torch.stack(norms), 2.0)
    torch._foreach_mul_(grads, torch.clamp(max_norm / (total + 1e-6), max=1.0))
    return total, parts
