"""Novel-view videos of a scene and PLY export of the Gaussians predicted for one view.

The camera path: an interpolation from the first context camera to the second (positions
linearly, rotations by quaternion slerp) and back, then a wobble (a small circle of the
camera centre in its image plane, looking at the same point) around each. Every frame is a
target view: UniqueSplat (c) predicts Gaussians per frame, in batches of ``chunk`` frames.
"""

import logging
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger(__name__)


def _quat(m: torch.Tensor) -> torch.Tensor:
    from usplat_dr.geometry.quaternions import matrix_to_quat_wxyz

    return torch.from_numpy(matrix_to_quat_wxyz(m[None].double().numpy())[0])


def _matrix(q: torch.Tensor) -> torch.Tensor:
    from usplat_dr.geometry.quaternions import quat_xyzw_to_matrix

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


@torch.no_grad()
def render_path(model, batch: dict, frames: int = 60, chunk: int = 8,
                device: torch.device | str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Colour [F, H, W, 3] and alpha-normalised depth [F, H, W] along ``camera_path``."""
    from usplat_dr.training import scene_args

    device = torch.device(device)
    args = scene_args(batch, device)
    images, k, e, near, far = args[:5]
    path = camera_path(e[0].cpu(), frames).to(device)
    colors, depths = [], []
    for s in range(0, frames, chunk):
        c = path[s:s + chunk][None]
        n = c.shape[1]
        out = model(images, k, e, near, far, k[:, :1].expand(1, n, 3, 3), c,
                    near[:, :1].expand(1, n), far[:, :1].expand(1, n))
        colors.append(out.color[0].clamp(0, 1).permute(0, 2, 3, 1).cpu())
        depths.append((out.depth[0] / out.alpha[0].clamp(min=1e-3)).cpu())
    return torch.cat(colors).numpy(), torch.cat(depths).numpy()


def write_video(frames: np.ndarray, path: str | os.PathLike, fps: int = 20) -> Path:
    """MP4 through ffmpeg when it is installed, otherwise an animated GIF (PIL). Returns the
    path written (its suffix says which)."""
    from PIL import Image

    from usplat_dr.images import to_uint8
    from usplat_dr.io import atomic_open

    path = Path(path)
    data = to_uint8(frames)
    h, w = data.shape[1:3]
    if shutil.which("ffmpeg"):
        target = path.with_suffix(".mp4")
        tmp = target.with_name(f".{target.name}.tmp.mp4")
        cmd = ["ffmpeg", "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24",
               "-s", f"{w}x{h}", "-r", str(fps), "-i", "-", "-pix_fmt", "yuv420p",
               "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", str(tmp)]
        subprocess.run(cmd, input=data.tobytes(), check=True)
        os.replace(tmp, target)
        return target
    target = path.with_suffix(".gif")
    imgs = [Image.fromarray(f) for f in data]
    with atomic_open(target, "wb") as f:
        imgs[0].save(f, format="GIF", save_all=True, append_images=imgs[1:],
                     duration=int(1000 / fps), loop=0)
    return target
