"""What ``usplat demo`` and ``usplat bench`` share: the demo's run recipe, defined in
``usplat_dr.training.budgets`` (budgets, the training run's config, the synthetic data), and
the shipped checkpoints it starts from (``usplat_dr.training.checkpoints``'s ``BASE``,
``SHIPPED``, ``BUDGETED``), re-exported here for the jobs; new code imports them from where they are
defined."""

from usplat_dr.model.uniquesplat import VARIANTS
from usplat_dr.training.budgets import (
    BUDGETS,
    CONFIG,
    FINETUNE_LR,
    PRESET,
    Budget,
    ensure_data,
    training_config,
)
from usplat_dr.training.checkpoints import BASE, BUDGETED, SHIPPED

__all__ = ["BASE", "BUDGETED", "BUDGETS", "CONFIG", "FINETUNE_LR", "PRESET", "SHIPPED",
           "VARIANTS", "Budget", "ensure_data", "training_config"]
