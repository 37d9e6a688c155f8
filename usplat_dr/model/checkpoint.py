"""MVSplat checkpoints in and out, strictly, with errors that say what does not match.

Official checkpoints are PyTorch Lightning files whose ``state_dict`` keys all start with
``encoder.`` (docs/mvsplat_notes.md sec. 1); downstream projects strip that prefix, as we do.
"""

import dataclasses
import os
from pathlib import Path

from torch import Tensor, nn

from usplat_dr.io import load_torch_file, torch_save

PREFIX = "encoder."


class CheckpointMismatchError(ValueError):
    """A state dict that does not fit the network: lists missing and unexpected keys and
    shape mismatches."""


def read_checkpoint(checkpoint, map_location="cpu", trust_checkpoint: bool = False) -> dict:
    """A checkpoint as a dict: ``checkpoint`` is a path or an already loaded dict. Files load
    with ``weights_only=True``; a file that needs arbitrary unpickling is refused unless
    ``trust_checkpoint`` (it can run code)."""
    if isinstance(checkpoint, dict):
        return checkpoint
    if not isinstance(checkpoint, (str, os.PathLike)):
        raise ValueError(f"checkpoint must be a path or a dict, got {type(checkpoint).__name__}")
    path = Path(checkpoint)
    if not path.is_file():
        raise FileNotFoundError(
            f"checkpoint file {str(path)!r} does not exist; download the MVSplat checkpoint "
            f"(e.g. re10k.ckpt from the MVSplat release) and pass its path")
    return load_torch_file(path, "checkpoint", map_location, trust=trust_checkpoint,
                           trust_hint="trust_checkpoint=True")


def extract_state_dict(ckpt: dict) -> dict[str, Tensor]:
    """The encoder's weights with the ``encoder.`` prefix stripped: from a Lightning
    checkpoint (``ckpt["state_dict"]``) or a bare state dict, prefixed or not."""
    sd = ckpt.get("state_dict", ckpt)
    if not isinstance(sd, dict) or not all(isinstance(v, Tensor) for v in sd.values()):
        raise ValueError("checkpoint must be a state dict (name -> tensor) or hold one under "
                         "'state_dict'")
    if any(k.startswith(PREFIX) for k in sd):
        return {k[len(PREFIX):]: v for k, v in sd.items() if k.startswith(PREFIX)}
    return dict(sd)


def check_state_dict(module: nn.Module | dict, sd: dict[str, Tensor],
                     what: str = "checkpoint") -> None:
    """Raise ``CheckpointMismatchError`` unless ``sd`` has exactly ``module``'s keys and
    shapes (``module`` may also be a dict of the expected tensors or shapes)."""
    own = module if isinstance(module, dict) else module.state_dict()
    own = {k: tuple(v.shape) if isinstance(v, Tensor) else tuple(v) for k, v in own.items()}
    missing = sorted(set(own) - set(sd))
    unexpected = sorted(set(sd) - set(own))
    shapes = sorted(f"{k}: checkpoint {list(sd[k].shape)} vs network {list(own[k])}"
                    for k in set(own) & set(sd) if tuple(sd[k].shape) != own[k])
    if missing or unexpected or shapes:
        def listing(name, items):
            head = "\n    ".join(items[:20])
            more = f"\n    ... and {len(items) - 20} more" if len(items) > 20 else ""
            return f"\n  {len(items)} {name}:\n    {head}{more}" if items else ""

        first = "; ".join(f"{name} {items[0]}" for name, items in (
            ("first missing key", missing), ("first unexpected key", unexpected),
            ("first shape mismatch", shapes)) if items)
        raise CheckpointMismatchError(
            f"{what} does not match the network ({len(own)} keys expected, {len(sd)} given; "
            f"{first}):"
            + listing("missing keys", missing) + listing("unexpected keys", unexpected)
            + listing("shape mismatches", shapes)
            + "\n  (is the configuration the checkpoint's? MVSplat's RE10K/ACID/DTU checkpoints "
              "use the default PrimaryNetworkCfg)")


def load_mvsplat_state_dict(module: nn.Module, checkpoint, map_location="cpu",
                            trust_checkpoint: bool = False) -> nn.Module:
    """Load an MVSplat checkpoint (path, Lightning dict or bare state dict) into ``module``
    strictly; returns ``module``."""
    sd = extract_state_dict(read_checkpoint(checkpoint, map_location, trust_checkpoint))
    what = (f"checkpoint {checkpoint}" if isinstance(checkpoint, (str, os.PathLike))
            else "checkpoint")
    check_state_dict(module, sd, what)
    module.load_state_dict(sd, strict=True)
    return module


def export_mvsplat_checkpoint(module: nn.Module, path: str | os.PathLike, global_step: int = 0
                              ) -> Path:
    """Write ``module``'s weights as an MVSplat-style checkpoint (``state_dict`` with
    ``encoder.`` keys), atomically; MVSplat's own code loads it with its usual ``ckpt_path``."""
    sd = {PREFIX + k: v.detach().cpu().clone() for k, v in module.state_dict().items()}
    ckpt = {"state_dict": sd, "global_step": int(global_step), "epoch": 0,
            "pytorch-lightning_version": "2.0.0"}
    cfg = getattr(module, "cfg", None)
    if dataclasses.is_dataclass(cfg):
        ckpt["usplat_config"] = dataclasses.asdict(cfg)
    return torch_save(ckpt, path)


def load_gmdepth_backbone(module: nn.Module, checkpoint, map_location="cpu",
                          trust_checkpoint: bool = False) -> nn.Module:
    """Initialise the CNN and transformer of a ``PrimaryNetwork`` from UniMatch's GMDepth
    checkpoint (``gmdepth-scale1-resumeflowthings-scannet-5d9d7964.pth``: weights under
    ``model``, keys ``backbone.*`` and ``transformer.*``), as MVSplat does for training from
    scratch. Every backbone key must be present with its shape; other keys are ignored."""
    ckpt = read_checkpoint(checkpoint, map_location, trust_checkpoint)
    sd = ckpt.get("model", ckpt.get("state_dict", ckpt))
    picked = {k: v for k, v in sd.items() if k.split(".")[0] in ("backbone", "transformer")}
    target = module.backbone
    check_state_dict(target, picked, what="GMDepth backbone checkpoint")
    target.load_state_dict(picked, strict=True)
    return module
