"""Quaternions, real part last (``xyzw``, scipy's and MVSplat's order)."""

import torch
from jaxtyping import Float
from torch import Tensor


def quat_xyzw_to_matrix(quats_xyzw: Float[Tensor, "*batch 4"]) -> Float[Tensor, "*batch 3 3"]:
    """Rotation matrices of (not necessarily unit) quaternions; normalised first, as MVSplat's
    Gaussian adapter does (q / (|q| + 1e-8)).

    Examples:
        >>> q = torch.tensor([0.0, 0.0, 1.0, 1.0])  # 90 degrees about +z
        >>> quat_xyzw_to_matrix(q).round(decimals=6).tolist()
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    """
    q = quats_xyzw / (quats_xyzw.norm(dim=-1, keepdim=True) + 1e-8)
    x, y, z, w = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(*q.shape[:-1], 3, 3)
