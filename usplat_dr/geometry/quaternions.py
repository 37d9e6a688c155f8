"""Quaternions, real part last (``xyzw``, scipy's and MVSplat's order)."""

import torch
from jaxtyping import Float
from torch import Tensor


def quat_xyzw_to_matrix(quats_xyzw: Float[Tensor, "*batch 4"], eps: float = 1e-8
                        ) -> Float[Tensor, "*batch 3 3"]:
    """Rotation matrices of (not necessarily unit) quaternions: pytorch3d's formula with
    ``two_s = 2 / (|q|^2 + eps)``, which divides out the norm; MVSplat's Gaussian adapter uses
    exactly this (so its covariances are reproduced to the bit).

    Examples:
        >>> q = torch.tensor([0.0, 0.0, 1.0, 1.0])  # 90 degrees about +z
        >>> quat_xyzw_to_matrix(q).round(decimals=6).tolist()
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    """
    i, j, k, r = torch.unbind(quats_xyzw, dim=-1)
    two_s = 2 / ((quats_xyzw * quats_xyzw).sum(dim=-1) + eps)
    o = torch.stack((1 - two_s * (j * j + k * k), two_s * (i * j - k * r), two_s * (i * k + j * r),
                     two_s * (i * j + k * r), 1 - two_s * (i * i + k * k), two_s * (j * k - i * r),
                     two_s * (i * k - j * r), two_s * (j * k + i * r), 1 - two_s * (i * i + j * j)),
                    dim=-1)
    return o.unflatten(-1, (3, 3))
