"""Videos: MP4 through ffmpeg (the binary imageio-ffmpeg ships, the ``video`` extra, or a system
ffmpeg), else an animated GIF."""

import logging
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
from PIL import Image

from usplat_dr.io.atomic import atomic_open, refuse_special
from usplat_dr.io.images import to_uint8

log = logging.getLogger(__name__)

MP4_HINT = "for mp4: pip install 'usplat-dr[video]' (imageio-ffmpeg ships an ffmpeg binary)"


def ffmpeg_exe() -> str | None:
    """The ffmpeg binary to write MP4 with: imageio-ffmpeg's own (the ``video`` extra), else
    one on ``PATH``, else ``None``."""
    try:  # optional (the ``video`` extra): imported only when a video is written
        import imageio_ffmpeg
    except ImportError:
        return shutil.which("ffmpeg")
    try:
        return imageio_ffmpeg.get_ffmpeg_exe()
    except RuntimeError:  # no binary for this platform in the wheel, none on PATH
        return shutil.which("ffmpeg")


def write_video(frames: np.ndarray, path: str | os.PathLike, fps: int = 20) -> Path:
    """MP4 through ffmpeg (``ffmpeg_exe``), otherwise an animated GIF (PIL) and a one-line
    message saying how to get MP4. ``frames``: ``[N, H, W, 3]`` floats in [0, 1] (clipped).
    Returns the path written (its suffix says which).

    Examples:
        >>> import tempfile
        >>> frames = np.zeros((2, 16, 16, 3), np.float32)
        >>> write_video(frames, Path(tempfile.mkdtemp()) / "clip").suffix in (".mp4", ".gif")
        True
    """
    if frames.ndim != 4 or frames.shape[-1] != 3 or len(frames) == 0:
        raise ValueError(f"frames must have shape (N, H, W, 3) with N >= 1, got "
                         f"{tuple(frames.shape)}")
    path = Path(path)
    data = to_uint8(frames)
    h, w = data.shape[1:3]
    exe = ffmpeg_exe()
    if exe is not None:
        target = path.with_suffix(".mp4")
        refuse_special(target)
        tmp = target.with_name(f".{target.name}.tmp.mp4")
        cmd = [exe, "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24",
               "-s", f"{w}x{h}", "-r", str(fps), "-i", "-", "-pix_fmt", "yuv420p",
               "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", str(tmp)]
        subprocess.run(cmd, input=data.tobytes(), check=True)
        os.replace(tmp, target)
        return target
    target = path.with_suffix(".gif")
    log.warning("no ffmpeg found: writing an animated GIF, %s; %s", target, MP4_HINT)
    imgs = [Image.fromarray(f) for f in data]
    with atomic_open(target, "wb") as f:
        imgs[0].save(f, format="GIF", save_all=True, append_images=imgs[1:],
                     duration=int(1000 / fps), loop=0)
    return target
