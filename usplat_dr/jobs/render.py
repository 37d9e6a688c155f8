"""``usplat render``: novel views of a scene, colour | depth, as a video and PNG frames.

The scene is an evaluation example of a dataset (``--data``) or the user's own images with a
camera file (``--images A B --cameras FILE``: a COLMAP model folder or a nerfstudio
transforms.json). The targets follow a path (``--path orbit``, ``usplat_dr.geometry.
camera_paths``: context 0 -> 1 -> 0, then a wobble around each) or are the cameras of another
camera file (``--path FILE``). Every frame is a target view: UniqueSplat (c) predicts
Gaussians per frame (``UniqueSplat.predict``), in batches of ``chunk`` frames; with
``--images`` the Gaussians of the first frame are also written as a 3DGS PLY.
"""

import argparse
import logging
import shutil
from pathlib import Path

import numpy as np
import torch

from usplat_dr.data.types import model_inputs
from usplat_dr.data.user_views import (
    read_cameras,
    target_cameras,
)
from usplat_dr.geometry.camera_paths import camera_path
from usplat_dr.io.images import colorize_depth, save_png
from usplat_dr.io.video import write_video
from usplat_dr.jobs.arguments import (
    add_example_arguments,
    add_own_views_arguments,
    between,
    budget_from_args,
    check_budget_arguments,
    fit_checkpoint,
    image_shape,
    one_example,
    out_folder,
    own_views,
)
from usplat_dr.model.ply import write_ply
from usplat_dr.model.predict import Prediction
from usplat_dr.training.loader import load

log = logging.getLogger(__name__)

def add_arguments(p: argparse.ArgumentParser) -> None:
    add_example_arguments(p, data_required=False)
    add_own_views_arguments(p)
    p.add_argument("--path", default="orbit", help="the target cameras: 'orbit' (context 0 -> "
                   "1 -> 0, then a wobble around each) or a camera file like --cameras")
    p.add_argument("--frames", type=between(2, MAX_PATH_CAMERAS), default=60,
                   help=f"frames of the orbit (at most {MAX_PATH_CAMERAS:,}, as a --path file's "
                   f"cameras)")
    p.add_argument("--out", type=out_folder, default="outputs/render/video",
                   help="output folder")


def run(args: argparse.Namespace) -> int:
    if args.images is None and args.data is None:
        raise ValueError("give --data (a dataset in the chunk format) or --images A B "
                         "--cameras FILE (your own images)")
    if args.images is not None and args.data is not None:
        raise ValueError("give --data or --images, not both")
    check_budget_arguments(args)
    out = Path(args.out)
    fit_checkpoint(args)
    if args.data is not None:
        model, batch = one_example(args)
        colors, depths = render_path(model, batch, args.frames, device=args.device,
                                     path=args.path, image_shape=image_shape(args),
                                     budget=budget_from_args(args))
    else:
        model = load(args.checkpoint, args.device, args.trust_checkpoint)
        pred = predict_own_views(model, args)
        colors = pred.color.permute(0, 2, 3, 1).cpu().numpy()
        depths = pred.depth.cpu().numpy()
        ply = write_ply(out / "gaussians_frame0000.ply", pred.gaussians[0])
        print(f"wrote {ply}: the Gaussians predicted for frame 0")
    frames = colour_and_depth(colors, depths)
    write_frames(frames, out / "frames")
    path = write_video(frames, out / "video")
    print(f"wrote {path} and {out / 'frames'} ({len(frames)} frames: colour | depth)")
    return 0


def write_frames(frames: np.ndarray, folder: Path) -> None:
    """``frames`` as ``folder/NNNN.png``, replacing the folder whole: written into a sibling
    first and swapped in, so that a longer earlier render's frames never mix with these, and
    a render killed before the swap leaves the earlier frames as they were (killed between
    the swap's two renames, no frames folder; the next render removes what is left)."""
    partial = folder.with_name(f".{folder.name}.partial")
    earlier = folder.with_name(f".{folder.name}.earlier")
    for left in (partial, earlier):  # what a killed render left
        if left.exists():
            shutil.rmtree(left)
    for i, frame in enumerate(frames):
        save_png(partial / f"{i:04d}.png", frame)
    if folder.is_symlink() or folder.is_file():
        raise ValueError(f"--out: {folder} is a link or a file, not a folder of frames: "
                         f"choose another --out")
    if folder.exists():  # moved aside, not deleted, until the new frames are in place
        folder.rename(earlier)
    partial.rename(folder)
    if earlier.exists():
        shutil.rmtree(earlier)


def colour_and_depth(colors: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """[F, H, 2W, 3] frames: colour beside depth, coloured between its 2nd and 98th
    percentiles over all frames."""
    valid = depths[np.isfinite(depths) & (depths > 0)]
    lo, hi = ((float(np.percentile(valid, 2)), float(np.percentile(valid, 98))) if valid.size
              else (1.0, 2.0))
    return np.concatenate([colors, np.stack([colorize_depth(d, near=lo, far=hi)
                                             for d in depths])], axis=2)


def targets(path: str, context_extrinsics: torch.Tensor, context_intrinsics: torch.Tensor,
            frames: int, image_shape: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """``--path``: the target cameras (extrinsics [N, 4, 4], intrinsics [N, 3, 3]): the orbit
    around the context cameras, seen with the first context camera's intrinsics, or the
    cameras of a camera file (at most ``MAX_PATH_CAMERAS``, for either source)."""
    if path == "orbit":
        e = camera_path(context_extrinsics.cpu(), frames).float()
        return e, context_intrinsics[:1].cpu().expand(len(e), 3, 3)
    e, k = target_cameras(read_cameras(path, what="--path"), image_shape)
    if len(e) > MAX_PATH_CAMERAS:
        raise ValueError(f"--path {path} holds {len(e):,} cameras (at most "
                         f"{MAX_PATH_CAMERAS:,} frames): keep every k-th camera, or split the "
                         f"file and render the parts")
    return e, k


#: Target cameras a ``--path`` file may hold: each is a frame (and, in (c), a set of Gaussians
#: of its own); a video path is tens to hundreds of frames.
MAX_PATH_CAMERAS = 2000
#: Targets predicted at once: memory stays that of ``PATH_CHUNK`` targets' Gaussians, however
#: long the path.
PATH_CHUNK = 8


def predict_own_views(model, args: argparse.Namespace) -> Prediction:
    """``--images`` and ``--cameras``: the model's ``Prediction`` for ``--path``, predicted
    ``PATH_CHUNK`` targets at a time, ``gaussians`` holding the first target's only (what
    ``run`` writes as a PLY)."""
    views, near, far = own_views(args, model.trained_depth_range, Path(args.out) / "pose")
    te, tk = targets(args.path, views.extrinsics, views.intrinsics, args.frames,
                     tuple(views.images.shape[-2:]))
    return model.predict(views.images, intrinsics=views.intrinsics,
                         extrinsics=views.extrinsics, target_intrinsics=tk,
                         target_extrinsics=te, near=near, far=far, chunk=PATH_CHUNK,
                         budget=budget_from_args(args), all_gaussians=False)


def render_path(model, batch: dict, frames: int = 60, chunk: int = 8,
                device: torch.device | str = "cpu", path: str = "orbit",
                image_shape: tuple[int, int] | None = None, budget=None,
                rank_by: str | None = None, tolerance: float | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Colour [F, H, W, 3] and alpha-normalised depth [F, H, W] of an example's scene along
    ``--path`` (``targets``), with ``budget`` Gaussians per frame (``None``: all)."""
    inputs = model_inputs(batch, torch.device(device))
    shape = image_shape or tuple(inputs.images.shape[-2:])
    te, tk = targets(path, inputs.extrinsics[0], inputs.intrinsics[0], frames, shape)
    pred = model.predict(inputs.images[0], intrinsics=inputs.intrinsics[0],
                         extrinsics=inputs.extrinsics[0], target_intrinsics=tk,
                         target_extrinsics=te, near=inputs.near[0], far=inputs.far[0],
                         chunk=chunk, budget=budget, rank_by=rank_by, tolerance=tolerance)
    return (pred.color.permute(0, 2, 3, 1).cpu().numpy(), pred.depth.cpu().numpy())
