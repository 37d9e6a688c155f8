"""What training shows of its validation scene: the scene (the dataset's first test example,
else a training one), the view-specificity meter on it for ``metrics.csv``, and a PNG grid."""

from pathlib import Path

import torch
from torch.utils.data import default_collate

from usplat_dr.data.dataset import ChunkDataset, dataset_from_section
from usplat_dr.data.types import model_inputs
from usplat_dr.evaluation import view_specificity
from usplat_dr.evaluation.figures import save_comparison


def validation_batch(dataset_config, fallback: dict) -> dict:
    """The first example of the validation stage (the dataset's test folder) when there is
    one, else ``fallback`` (a training batch)."""
    try:
        ds = dataset_from_section(dataset_config, "val")
        example = next(iter(ds), None) if isinstance(ds, ChunkDataset) else None
    except (ValueError, FileNotFoundError, StopIteration):
        example = None
    if example is None:
        first = {side: {k: v[:1] for k, v in fallback[side].items()}
                 for side in ("context", "target")}
        return {**first, "scene": fallback["scene"][:1]}  # save_comparison names it
    return default_collate([example])


def view_meter(model, batch: dict | None, device) -> dict:
    """The view-specificity meter (``usplat_dr.evaluation.view_specificity``) on the
    validation scene ``batch``, for metrics.csv at validation steps that write a row:
    ``view_spread`` (how much Delta W differs between its targets, relative to ||W||, the
    largest over the layers) and, in dB, ``view_psnr_abs`` (mean |PSNR(per-target Delta W) -
    PSNR(the scene's mean)|) and ``view_psnr_zero`` (PSNR(per-target) - PSNR(Delta W = 0)).
    ``{}`` for a model without the view-specific branch or a validation scene with one
    target."""
    if (batch is None or getattr(model, "specific", None) is None
            or batch["target"]["image"].shape[1] < 2):
        return {}
    (r,) = view_specificity.read_batch(model, batch, device)
    return {"view_spread": max(r.spread.values()), "view_psnr_abs": r.d_mean_abs,
            "view_psnr_zero": r.d_zero}


@torch.no_grad()
def validation_grid(model, batch: dict, device, out: Path, step: int) -> Path:
    """``out/validation/step_NNNNNNN_<scene>.png``: context | target | prediction | depth, a
    row per target view (``model`` is put in evaluation mode)."""
    model.eval()
    pred = model(*model_inputs(batch, device))
    return save_comparison(out / "validation", batch, pred, prefix=f"step_{step:07d}_")
