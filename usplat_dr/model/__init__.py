"""Torch models: the primary network (MVSplat's encoder) and its checkpoints, and UniqueSplat
(the primary network steered by view-agnostic and view-specific hypernetworks).

UniqueSplat and its configuration are imported on first use (PEP 562): it brings the
Dr.Jit rasteriser, whose libraries take ~60 MiB and ~0.15 s, which a user of the primary
network alone (e.g. loading an MVSplat checkpoint) does not need."""

from usplat_dr.model.checkpoint import (
    CheckpointMismatchError,
    export_mvsplat_checkpoint,
    load_gmdepth_backbone,
    load_mvsplat_state_dict,
)
from usplat_dr.model.encoder import PrimaryNetwork, PrimaryNetworkCfg
from usplat_dr.model.types import Gaussians

_LAZY = ("PRESETS", "UniqueSplat", "UniqueSplatCfg", "UniqueSplatOutput")

__all__ = ["PRESETS", "CheckpointMismatchError", "Gaussians", "PrimaryNetwork",
           "PrimaryNetworkCfg", "UniqueSplat", "UniqueSplatCfg", "UniqueSplatOutput",
           "export_mvsplat_checkpoint", "load_gmdepth_backbone", "load_mvsplat_state_dict"]


def __getattr__(name: str):
    if name in _LAZY:
        from usplat_dr.model import uniquesplat  # lazy: it loads Dr.Jit (docstring)

        return getattr(uniquesplat, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
