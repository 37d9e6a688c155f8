"""Classical predictors every model is scored against.

``copy_nearest``: the target view predicted as the context image whose camera centre is
nearest the target's (no geometry at all). On hand-held captures neighbouring photos look
alike, so this trivial predictor scores well; a model's margin over it (``psnr_over_copy``
in ``usplat eval``) says what the 3D reasoning adds. On the synthetic held-out standard split
the shipped (a) beats it by about 5.6 dB (2026-12-01); on real photographs by about nothing.
"""

import torch
from jaxtyping import Float, Int
from torch import Tensor


def nearest_context(
    context_extrinsics: Float[Tensor, "context 4 4"],  # camera-to-world
    target_extrinsics: Float[Tensor, "target 4 4"],
) -> Int[Tensor, " target"]:
    """The index of the context camera whose centre is nearest each target's (Euclidean;
    the first of equals).

    Examples:
        >>> c = torch.eye(4).repeat(2, 1, 1); c[1, 0, 3] = 1.0
        >>> t = torch.eye(4).repeat(3, 1, 1); t[:, 0, 3] = torch.tensor([0.1, 0.9, 0.5])
        >>> nearest_context(c, t).tolist()
        [0, 1, 0]
    """
    centres_c = context_extrinsics[:, :3, 3].double()
    centres_t = target_extrinsics[:, :3, 3].double()
    return torch.cdist(centres_t, centres_c).argmin(dim=1)


def copy_nearest(
    context_images: Float[Tensor, "context 3 h w"],
    context_extrinsics: Float[Tensor, "context 4 4"],
    target_extrinsics: Float[Tensor, "target 4 4"],
) -> Float[Tensor, "target 3 h w"]:
    """Each target predicted as the context image nearest it (``nearest_context``)."""
    return context_images[nearest_context(context_extrinsics, target_extrinsics)]
