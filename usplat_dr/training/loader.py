"""``usplat_dr.load``: a ``UniqueSplat`` from any checkpoint users have, by one door."""

import os

import torch

from usplat_dr.model import CheckpointMismatchError, UniqueSplat
from usplat_dr.training.checkpoints import (
    _built,
    is_mvsplat_checkpoint,
    read_usplat_checkpoint,
)
from usplat_dr.training.registry import default_checkpoint, resolve_checkpoint


def load(checkpoint: str | os.PathLike | None = None, device: torch.device | str = "cpu",
         trust: bool = False, image_shape: tuple[int, int] | None = (64, 64)) -> UniqueSplat:
    """A ``UniqueSplat`` in evaluation mode from any checkpoint users have: a shipped one by
    name (``usplat_dr.load("full-64")``; ``usplat models`` lists them), a file ``usplat
    train`` wrote, or an official MVSplat checkpoint (``re10k.ckpt``: the paper preset (a),
    which renders what MVSplat renders). ``None``: the shipped (c) for images of
    ``image_shape`` (``None``: your own photographs, larger than any; the commands' default).
    ``trust``: full unpickling, for files ``torch.load(weights_only=True)`` refuses (MVSplat's
    Lightning files may need it; it can run code: only for files you trust). The file is read
    once (``read_usplat_checkpoint`` keeps the last files read).

    Examples:
        >>> model = load("full-64")
        >>> model.cfg.variant
        'full'
    """
    if checkpoint is None:
        checkpoint = default_checkpoint(image_shape)[0]
    path = resolve_checkpoint(checkpoint)
    state = read_usplat_checkpoint(path, device, trust)
    if is_mvsplat_checkpoint(state):
        model = UniqueSplat.from_preset("paper", variant="baseline")
        try:
            model.load_mvsplat(state)
        except CheckpointMismatchError as e:  # the file the user named, first
            raise CheckpointMismatchError(f"{path}: {e}") from None
        return model.to(device).eval()
    return _built(path, state, device)[0]
