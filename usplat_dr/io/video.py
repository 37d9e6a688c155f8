"""Videos: MP4 through ffmpeg when it is installed, else an animated GIF."""

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
from PIL import Image

from usplat_dr.io.atomic import atomic_open, refuse_special
from usplat_dr.io.images import to_uint8


def write_video(frames: np.ndarray, path: str | os.PathLike, fps: int = 20) -> Path:
    """MP4 through ffmpeg when it is installed, otherwise an animated GIF (PIL). Returns the
    path written (its suffix says which)."""
    path = Path(path)
    data = to_uint8(frames)
    h, w = data.shape[1:3]
    if shutil.which("ffmpeg"):
        target = path.with_suffix(".mp4")
        refuse_special(target)
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
