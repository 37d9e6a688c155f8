"""Camera paths for novel-view videos: an interpolation from the first context camera to the
second (positions linearly, rotations by quaternion slerp) and back, then a wobble (a small
circle of the camera centre in its image plane, looking at the same point) around each."""

import numpy as np
import torch

from usplat_dr.geometry.quaternions import matrix_to_quat_wxyz, quat_xyzw_to_matrix


def _quat(m: torch.Tensor) -> torch.Tensor:
    return torch.from_numpy(matrix_to_quat_wxyz(m[None].double().numpy())[0])


def _matrix(q: torch.Tensor) -> torch.Tensor:
    return quat_xyzw_to_matrix(torch.cat([q[1:], q[:1]]).double())


def slerp(q0: torch.Tensor, q1: torch.Tensor, t: float) -> torch.Tensor:
    dot = float((q0 * q1).sum())
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + t * (q1 - q0)
        return q / q.norm()
    theta = np.arccos(dot)
    return (np.sin((1 - t) * theta) * q0 + np.sin(t * theta) * q1) / np.sin(theta)


def camera_path(extrinsics: torch.Tensor, frames: int = 60, wobble: float = 0.25
                ) -> torch.Tensor:
    """[frames, 4, 4] camera-to-world matrices: context 0 -> 1 -> 0, then a wobble of radius
    ``wobble`` x the context baseline around each context camera."""
    c0, c1 = extrinsics[0].double(), extrinsics[1].double()
    q0, q1 = _quat(c0[:3, :3]), _quat(c1[:3, :3])
    n_interp = frames // 2
    n_wobble = frames - n_interp
    out = []
    for i in range(n_interp):
        t = 0.5 - 0.5 * np.cos(2 * np.pi * i / n_interp)  # 0 -> 1 -> 0, smooth
        m = torch.eye(4, dtype=torch.float64)
        m[:3, :3] = _matrix(slerp(q0, q1, t))
        m[:3, 3] = (1 - t) * c0[:3, 3] + t * c1[:3, 3]
        out.append(m)
    radius = wobble * float((c1[:3, 3] - c0[:3, 3]).norm())
    for i in range(n_wobble):
        base = c0 if i < n_wobble // 2 else c1
        a = 2 * np.pi * i / max(n_wobble // 2, 1)
        m = base.clone()
        m[:3, 3] = base[:3, 3] + radius * (np.cos(a) * base[:3, 0] + np.sin(a) * base[:3, 1])
        out.append(m)
    return torch.stack(out).float()
