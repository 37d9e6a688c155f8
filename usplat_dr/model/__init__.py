"""Torch models: the primary network (MVSplat's encoder) and its checkpoints."""

from usplat_dr.model.checkpoint import (
    CheckpointMismatchError,
    export_mvsplat_checkpoint,
    load_gmdepth_backbone,
    load_mvsplat_state_dict,
)
from usplat_dr.model.encoder import PrimaryNetwork, PrimaryNetworkCfg
from usplat_dr.model.types import Gaussians

__all__ = ["CheckpointMismatchError", "Gaussians", "PrimaryNetwork", "PrimaryNetworkCfg",
           "export_mvsplat_checkpoint", "load_gmdepth_backbone", "load_mvsplat_state_dict"]
