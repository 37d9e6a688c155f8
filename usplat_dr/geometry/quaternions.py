"""Quaternions, real part last (``xyzw``, scipy's and MVSplat's order)."""

import numpy as np
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


def matrix_to_quat_wxyz(rot: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) of rotation matrices [G, 3, 3] (Shepperd's method: the
    largest of w, x, y, z is computed first, so no division by a small number).

    Examples:
        >>> r = np.array([[[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]])  # 90 degrees about +z
        >>> matrix_to_quat_wxyz(r).round(6).tolist()
        [[0.707107, 0.0, 0.0, 0.707107]]
    """
    t = np.trace(rot, axis1=1, axis2=2)
    q = np.zeros((len(rot), 4))
    cases = np.stack([t, rot[:, 0, 0], rot[:, 1, 1], rot[:, 2, 2]], 1).argmax(1)
    for c in range(4):
        s = cases == c
        r = rot[s]
        if c == 0:
            w = np.sqrt(1 + t[s]) / 2
            q[s] = np.stack([w, (r[:, 2, 1] - r[:, 1, 2]) / (4 * w),
                             (r[:, 0, 2] - r[:, 2, 0]) / (4 * w),
                             (r[:, 1, 0] - r[:, 0, 1]) / (4 * w)], 1)
        else:
            i = c - 1
            j, k = (i + 1) % 3, (i + 2) % 3
            v = np.sqrt(1 + r[:, i, i] - r[:, j, j] - r[:, k, k]) / 2
            out = np.zeros((s.sum(), 4))
            out[:, 0] = (r[:, k, j] - r[:, j, k]) / (4 * v)
            out[:, 1 + i] = v
            out[:, 1 + j] = (r[:, j, i] + r[:, i, j]) / (4 * v)
            out[:, 1 + k] = (r[:, k, i] + r[:, i, k]) / (4 * v)
            q[s] = out
    return q / np.linalg.norm(q, axis=1, keepdims=True)
