"""Videos: MP4 through imageio-ffmpeg's binary, read back frame by frame; an animated GIF with a
one-line hint when no ffmpeg is found; bad frame arrays named."""

import doctest
import logging

import numpy as np
import pytest
from PIL import Image

from usplat_dr.io import video
from usplat_dr.io.video import write_video


def smooth_frames(n: int = 6, h: int = 48, w: int = 64) -> np.ndarray:
    """``[n, h, w, 3]`` floats in [0, 1]: colour ramps that move a little from frame to frame
    (smooth content, as rendered views are, so a video codec keeps it close)."""
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w]).reshape(2, 1, 1)
    frames = [np.stack([x + 0.05 * t, y, 0.5 + 0.3 * np.sin(3 * x + t)], -1) for t in range(n)]
    return np.clip(np.stack(frames), 0, 1).astype(np.float32)


def test_mp4_through_imageio_ffmpeg_reads_back(tmp_path):
    imageio_ffmpeg = pytest.importorskip(
        "imageio_ffmpeg", reason="imageio-ffmpeg is not installed (pip install 'usplat-dr[video]')")
    frames = smooth_frames()
    path = write_video(frames, tmp_path / "clip.gif", fps=10)  # the suffix follows the format
    assert path == tmp_path / "clip.mp4" and path.is_file()
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    assert meta["size"] == (64, 48)  # (width, height)
    back = np.stack([np.frombuffer(f, np.uint8).reshape(48, 64, 3) for f in reader])
    assert back.shape == (6, 48, 64, 3)
    diff = np.abs(back.astype(np.float64) / 255 - frames)
    # H.264 is lossy and yuv420p halves the chroma resolution: on these smooth ramps the error
    # is a few grey levels on average (measured 0.0097 mean, 0.068 max with imageio-ffmpeg
    # 0.8.1's libx264 at its default quality). 0.03 mean and 0.2 max still fail a frame off by
    # one (0.076 mean from its source), reversed frames (0.13) or swapped channels (0.23).
    assert diff.mean() < 0.03 and diff.max() < 0.2, (diff.mean(), diff.max())
    for t in range(6):  # each frame is closest to its own source frame
        errors = [np.abs(back[t] / 255 - f).mean() for f in frames]
        assert int(np.argmin(errors)) == t, errors


def test_gif_without_ffmpeg_says_how_to_get_mp4(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(video, "ffmpeg_exe", lambda: None)
    frames = smooth_frames(n=3, h=20, w=30)
    with caplog.at_level(logging.WARNING, logger="usplat_dr.io.video"):
        path = write_video(frames, tmp_path / "clip")
    assert path == tmp_path / "clip.gif"
    assert "pip install 'usplat-dr[video]'" in caplog.text
    assert len(caplog.records) == 1 and "\n" not in caplog.records[0].getMessage()
    with Image.open(path) as gif:
        assert gif.n_frames == 3 and gif.size == (30, 20)


def test_ffmpeg_exe_prefers_imageio_ffmpeg():
    imageio_ffmpeg = pytest.importorskip(
        "imageio_ffmpeg", reason="imageio-ffmpeg is not installed (pip install 'usplat-dr[video]')")
    assert video.ffmpeg_exe() == imageio_ffmpeg.get_ffmpeg_exe()


@pytest.mark.parametrize("shape", [(0, 8, 8, 3), (8, 8, 3), (2, 8, 8, 4)])
def test_bad_frames_are_named(tmp_path, shape):
    with pytest.raises(ValueError, match=r"frames must have shape \(N, H, W, 3\)"):
        write_video(np.zeros(shape, np.float32), tmp_path / "clip")


def test_doctests_run():
    result = doctest.testmod(video)
    assert result.attempted > 0 and result.failed == 0, result
