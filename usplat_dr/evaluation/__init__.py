"""Evaluation with the field's protocol (``protocol``), its metrics (``metrics``, ``lpips``),
figures, paired comparisons with bootstrap intervals (``verdict``) and where the numbers came
from (``provenance``)."""

from usplat_dr.evaluation.protocol import (
    depth_metrics,
    evaluate,
    held_out_scenes,
    load_example,
    nan_mean,
    synthetic_indices,
)

__all__ = ["depth_metrics", "evaluate", "held_out_scenes", "load_example", "nan_mean",
           "synthetic_indices"]
