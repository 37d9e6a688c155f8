"""Torch models: the primary network (MVSplat's encoder) and its checkpoints, and UniqueSplat
(the primary network steered by view-agnostic and view-specific hypernetworks)."""

from usplat_dr.model.checkpoint import (
    CheckpointMismatchError,
    export_mvsplat_checkpoint,
    load_gmdepth_backbone,
    load_mvsplat_state_dict,
)
from usplat_dr.model.encoder import PrimaryNetwork, PrimaryNetworkCfg
from usplat_dr.model.types import Gaussians
from usplat_dr.model.uniquesplat import (
    PRESETS,
    UniqueSplat,
    UniqueSplatCfg,
    UniqueSplatOutput,
)

__all__ = ["PRESETS", "CheckpointMismatchError", "Gaussians", "PrimaryNetwork",
           "PrimaryNetworkCfg", "UniqueSplat", "UniqueSplatCfg", "UniqueSplatOutput",
           "export_mvsplat_checkpoint", "load_gmdepth_backbone", "load_mvsplat_state_dict"]
