"""Checkpoint files of training: a model from one (``load_model``), the primary network of a
trained (a) as the start of (b) and (c) (``init_from_checkpoint``), and a shippable copy of
one (``export_weights``)."""

import logging
import os
from pathlib import Path

import torch

from usplat_dr.config import ConfigError
from usplat_dr.io import load_torch_file, torch_save
from usplat_dr.model import UniqueSplat, UniqueSplatCfg

#: How a user opts in to full unpickling (named in the refusal's message).
TRUST_HINT = "--trust-checkpoint (usplat eval/render/export-ply/train) or trust=True"


def read_usplat_checkpoint(checkpoint: str | os.PathLike, map_location="cpu",
                           trust: bool = False) -> dict:
    """A usplat checkpoint file as a dict, loaded with ``torch.load(weights_only=True)``:
    ours hold tensors and plain data only. ``trust=True`` allows full unpickling (files
    written before RNG states were stored as plain data need it; it can run code)."""
    path = Path(checkpoint)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {str(path)!r} does not exist (usplat train writes "
                                f"OUTPUT_DIR/checkpoints/last.ckpt; shipped ones are in "
                                f"checkpoints/)")
    return load_torch_file(path, "checkpoint", map_location, trust=trust, trust_hint=TRUST_HINT)


def load_model(checkpoint: str | os.PathLike, device: torch.device | str = "cpu",
               trust: bool = False):
    """A ``UniqueSplat`` from a training checkpoint (``usplat train``'s ``last.ckpt``) or a
    shipped one, and its step. ``trust``: see ``read_usplat_checkpoint``."""
    path = Path(checkpoint)
    state = read_usplat_checkpoint(path, device, trust)
    if "model_config" not in state:
        raise ValueError(f"{path} is not a usplat training checkpoint (no 'model_config'); "
                         f"an MVSplat checkpoint loads with UniqueSplat.load_mvsplat")
    resnet_log = logging.getLogger("usplat_dr.model.hypernet.resnet")
    level = resnet_log.level
    resnet_log.setLevel(logging.ERROR)  # its weights come from the checkpoint, not a file
    try:
        model = UniqueSplat(UniqueSplatCfg.from_dict(state["model_config"]))
    finally:
        resnet_log.setLevel(level)
    model.load_state_dict(state["model"])
    return model.to(device).eval(), state.get("step", 0)


def training_image_shape(checkpoint: str | os.PathLike, trust: bool = False
                         ) -> tuple[int, int] | None:
    """The (H, W) a usplat checkpoint was trained at (its config's ``dataset.image_shape``),
    or ``None`` when the checkpoint does not record one."""
    state = read_usplat_checkpoint(checkpoint, trust=trust)
    shape = state.get("config", {}).get("dataset", {}).get("image_shape")
    return (int(shape[0]), int(shape[1])) if shape else None


def load_models(runs: dict, device) -> dict:
    """``{key: model}`` from ``{key: run folder}`` (each run's ``checkpoints/last.ckpt``)."""
    return {key: load_model(run / "checkpoints" / "last.ckpt", device)[0]
            for key, run in runs.items()}


def init_from_checkpoint(model, path: str | os.PathLike, trust: bool = False) -> None:
    """The paper's protocol: the primary network (encoder and predictor) from a trained
    usplat checkpoint (``usplat train``'s or a shipped one, any variant); for (b) and (c) its
    target layers' weights become W, and the hypernetworks' zero-initialised outputs make
    the model start exactly where that checkpoint is. ``trust``: see
    ``read_usplat_checkpoint`` (``model.trust_checkpoint``)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"model.init_from: checkpoint {str(path)!r} does not exist")
    state = read_usplat_checkpoint(path, trust=trust)
    if "model_config" not in state:
        raise ConfigError(f"model.init_from: {path} is not a usplat checkpoint (no "
                          f"'model_config'); an MVSplat checkpoint goes in model.init_mvsplat")
    sd = state["model"]
    if state["model_config"]["variant"] != "baseline":
        raise ConfigError(f"model.init_from: {path} holds variant "
                          f"{state['model_config']['variant']!r}; start from a baseline (a) "
                          f"checkpoint (its primary network is complete)")
    primary = {k.removeprefix("primary."): v.float() for k, v in sd.items()
               if k.startswith("primary.")}
    model.load_mvsplat(primary)


def export_weights(checkpoint: str | os.PathLike, out: str | os.PathLike, half: bool = True,
                   metadata: dict | None = None, trust: bool = False) -> Path:
    """A shippable copy of a training checkpoint: the model's weights (float16 when ``half``:
    half the bytes, and evaluation within 0.01 dB of float32, measured by
    ``train/ship_checkpoint.py``), its model config, training config, step, provenance and
    ``metadata``; no optimiser, scheduler or RNG state. Plain data only, so it loads with
    ``torch.load(weights_only=True)``; ``usplat eval/render/export-ply --checkpoint`` and
    ``model.init_from`` read it like a training checkpoint."""
    state = read_usplat_checkpoint(checkpoint, trust=trust)
    if "model_config" not in state:
        raise ValueError(f"checkpoint {checkpoint} is not a usplat training checkpoint")
    weights = {k: (v.half() if half and v.is_floating_point() else v).contiguous()
               for k, v in state["model"].items()}
    shipped = {"format": "usplat-weights/1", "model": weights,
               "model_config": state["model_config"], "config": state.get("config", {}),
               "step": state.get("step", 0), "provenance": state.get("provenance", {}),
               "metadata": metadata or {}}
    return torch_save(shipped, out)
