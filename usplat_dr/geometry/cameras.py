"""Camera conventions, written once.

- Extrinsics are camera-to-world (``c2w``) 4x4 matrices with OpenCV axes: +X right, +Y down,
  +Z forward (the data convention of pixelSplat/MVSplat).
- ``intrinsics`` are normalised: row 0 divided by the image width, row 1 by the height, so
  ``[[fx/W, 0, cx/W], [0, fy/H, cy/H], [0, 0, 1]]``; ``Ks`` are in pixels.
- A pixel (row i, column j) is sampled at (j + 0.5, i + 0.5) in pixel units.
"""

import torch
from jaxtyping import Float
from torch import Tensor


def look_at(
    eye: Float[Tensor, "*batch 3"],
    target: Float[Tensor, "*batch 3"],
    up: Float[Tensor, "*batch 3"],
) -> Float[Tensor, "*batch 4 4"]:
    """OpenCV camera-to-world matrices looking from ``eye`` at ``target``; ``up`` is world up
    (the camera's -Y axis points as close to it as possible).

    Examples:
        >>> c2w = look_at(torch.tensor([0.0, 0, -2]), torch.zeros(3), torch.tensor([0.0, -1, 0]))
        >>> c2w[:3, 2].tolist()  # +Z (forward) points from the eye to the target
        [0.0, 0.0, 1.0]
    """
    forward = torch.nn.functional.normalize(target - eye, dim=-1)  # +Z
    # +X = (+Y) x (+Z) with +Y (down) close to -up, so that the frame is right-handed.
    right = torch.nn.functional.normalize(torch.linalg.cross(-up, forward, dim=-1), dim=-1)
    down = torch.linalg.cross(forward, right, dim=-1)  # +Y
    c2w = torch.zeros(*eye.shape[:-1], 4, 4, dtype=eye.dtype, device=eye.device)
    c2w[..., :3, 0] = right
    c2w[..., :3, 1] = down
    c2w[..., :3, 2] = forward
    c2w[..., :3, 3] = eye
    c2w[..., 3, 3] = 1.0
    return c2w


def normalized_intrinsics(
    fx: float, fy: float, cx: float = 0.5, cy: float = 0.5, batch: tuple[int, ...] = ()
) -> Float[Tensor, "*batch 3 3"]:
    """Normalised intrinsics (fx, cx in units of the image width; fy, cy of its height)."""
    k = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return k.expand(*batch, 3, 3).clone()
