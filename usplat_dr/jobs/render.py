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

from usplat_dr.data.chunks import stored_image_shape
from usplat_dr.data.types import model_inputs
from usplat_dr.data.user_views import (
    UserViews,
    context_views,
    crop_advice,
    read_cameras,
    target_cameras,
)
from usplat_dr.evaluation import load_example, synthetic_indices
from usplat_dr.geometry.camera_paths import camera_path
from usplat_dr.geometry.plane_sweep import near_far_from_sweep
from usplat_dr.io.images import colorize_depth, save_png
from usplat_dr.io.video import write_video
from usplat_dr.jobs.arguments import (
    CHECKPOINT_HELP,
    DATASET_HELP,
    DEVICE_HELP,
    add_budget_arguments,
    at_least,
    check_budget_arguments,
    out_folder,
    positive_float,
    positive_int,
)
from usplat_dr.model.ply import write_ply
from usplat_dr.model.predict import Prediction
from usplat_dr.training.checkpoints import depth_range_warning, training_image_shape
from usplat_dr.training.loader import load
from usplat_dr.training.registry import default_checkpoint

log = logging.getLogger(__name__)

DATASETS = ["synth", "re10k", "acid", "dtu"]


def add_example_arguments(p: argparse.ArgumentParser, data_required: bool = True) -> None:
    """The arguments naming a model and one evaluation example (``render``, ``export-ply``)."""
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP)
    p.add_argument("--data", required=data_required, help="dataset root (chunk format)")
    p.add_argument("--dataset", default="synth", choices=DATASETS,
                   help=DATASET_HELP)
    p.add_argument("--index", help="evaluation index JSON (default: the synthetic set's "
                   "standard split)")
    p.add_argument("--scene", help="scene key (default: the first of the index)")
    add_image_shape_argument(p)
    add_trust_argument(p)
    add_budget_arguments(p)
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                   help=DEVICE_HELP)


def add_trust_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--trust-checkpoint", action="store_true",
                   help="unpickle the checkpoint fully if torch.load(weights_only=True) refuses "
                   "it (it can run code: only for files you trust)")


def add_image_shape_argument(p: argparse.ArgumentParser, fits: bool = True) -> None:
    """``--image-shape``; ``fits``: without --checkpoint the command's default model is the
    one for that size (``fit_checkpoint``), and its help says so."""
    fitted = ("; without --checkpoint, the shipped (c) trained nearest it, or nearest --data's "
              "stored size, or the largest for your own images" if fits else "")
    p.add_argument("--image-shape", type=positive_int, nargs=2, metavar=("H", "W"),
                   help="the size images are cropped and resized to (default: the size the "
                   f"checkpoint was trained at{fitted})")


def image_shape(args: argparse.Namespace) -> tuple[int, int]:
    """``--image-shape``, or the checkpoint's training image shape (the dataset preset's
    default, 256 x 256, for a checkpoint that records none)."""
    if args.image_shape:
        return tuple(args.image_shape)
    return training_image_shape(args.checkpoint, args.trust_checkpoint) or (256, 256)


def fit_checkpoint(args: argparse.Namespace) -> str:
    """``--checkpoint`` as given (a name never changes size: ``full-64`` is that model at any
    size); without one, the shipped (c) for the request, which ``args.checkpoint`` becomes
    (``default_checkpoint``): the one trained nearest ``--image-shape``, else nearest the size
    ``--data``'s images are stored at, else with your own ``--images`` the largest; said."""
    if args.checkpoint is not None:
        return args.checkpoint
    if args.image_shape is not None:
        shape = tuple(args.image_shape)
    elif getattr(args, "images", None) is not None:
        shape = None  # your own photographs: larger than any model's size
    else:
        data = getattr(args, "data", None)
        shape = stored_image_shape(data) if data is not None else None
        if shape is None:
            shape = (64, 64) if data is not None else None
    args.checkpoint, line = default_checkpoint(shape)
    log.info("%s", line)
    return args.checkpoint


def one_example(args: argparse.Namespace) -> tuple:
    """The model and the example that ``add_example_arguments``' arguments name."""
    index = args.index or synthetic_indices(args.data, ["standard"])["standard"]
    model = load(args.checkpoint, args.device, args.trust_checkpoint)
    return model, load_example(dataset_section(args), index, args.scene)


def dataset_section(args: argparse.Namespace) -> dict:
    """The dataset section of ``--data``, ``--dataset``, the image shape and, where given,
    ``--near``/``--far`` (overriding each scene's recorded range)."""
    dataset = {"name": args.dataset, "roots": [args.data], "image_shape": image_shape(args)}
    if hasattr(args, "near"):
        check_near_far(args)
        if args.near is not None:
            dataset["overrides"] = {"near": args.near, "far": args.far}
    return dataset


def add_own_views_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments naming a user's own context views (``render``, ``view``)."""
    own = p.add_argument_group("your own context views (instead of --data)")
    own.add_argument("--images", nargs="+", metavar="IMAGE",
                     help="two (or more) context images, named as in --cameras (without "
                     "--cameras they are posed by COLMAP first: usplat pose)")
    own.add_argument("--cameras", help="their cameras: a COLMAP model folder (sparse/0) or a "
                     "nerfstudio transforms.json (default: pose the images with COLMAP)")
    add_near_far_arguments(own, "from the COLMAP model's sparse points, else estimated by a "
                           "plane sweep between the two context views")
    own.add_argument("--ignore-distortion", action="store_true",
                     help="drop lens distortion coefficients (else they are an error)")


def add_near_far_arguments(p, default: str) -> None:
    """``--near`` and ``--far`` (scene units), ``default`` saying where they come from
    otherwise."""
    p.add_argument("--near", type=positive_float, help=f"near depth, scene units (default: "
                   f"{default})")
    p.add_argument("--far", type=positive_float, help="far depth (as --near)")


def check_own_views(args: argparse.Namespace) -> None:
    """The mistakes in ``add_own_views_arguments``' arguments that need no file read."""
    check_near_far(args)


def check_near_far(args: argparse.Namespace) -> None:
    if (args.near is None) != (args.far is None):
        raise ValueError("give both --near and --far, or neither")
    if args.near is not None and not args.near < args.far:
        raise ValueError(f"--near must be below --far, got {args.near} and {args.far}")


def pose_own_images(args: argparse.Namespace, folder: Path) -> None:
    """``--images`` without ``--cameras``: the images posed by COLMAP into ``folder``
    (``usplat_dr.data.pose``; reused when it already holds these photos' poses), then
    ``args.cameras`` its model and ``args.images`` its undistorted copies."""
    from usplat_dr import _threads  # (with pycolmap, only where photos are posed)
    from usplat_dr.data.pose import PoseSettings, pose_photos, posed_before

    photos = [Path(p) for p in args.images]
    result = posed_before(photos, folder)
    if result is None:
        print(f"no --cameras: posing the {len(photos)} photos with COLMAP (pycolmap) into "
              f"{folder} (usplat pose does this alone)")
        result = pose_photos(photos, folder, PoseSettings(threads=_threads.choose().threads))
    else:
        print(f"no --cameras: using the poses of these photos in {folder}")
    print(result.line())
    missing = [p.name for p in photos if p.name not in result.registered]
    if missing:
        raise ValueError(f"COLMAP could not pose {', '.join(missing)} (pose.json in {folder} "
                         "says why): give --cameras, or more photos of the scene with "
                         "usplat pose")
    args.cameras = str(result.model)
    args.images = [str(result.images / p.name) for p in photos]


def own_views(args: argparse.Namespace, trained_range: list[float] | None = None,
              pose_folder: Path | None = None) -> tuple[UserViews, float, float]:
    """The context views ``--images`` and ``--cameras`` name (posed first into
    ``pose_folder`` without ``--cameras``: ``pose_own_images``), cropped to ``image_shape``,
    and near/far (``--near``/``--far``, else from the sparse points, else estimated by a
    plane sweep between the first two views), printed, with a warning when they lie far
    outside ``trained_range`` (the model's ``trained_depth_range``)."""
    check_own_views(args)
    if args.cameras is None:
        from usplat_dr.data.pose import default_pose_folder  # only where photos are posed

        pose_own_images(args, pose_folder or default_pose_folder(args.images))
        posed = True
    else:
        posed = False
    scene, shape = read_cameras(args.cameras, args.ignore_distortion), image_shape(args)
    views = context_views(args.images, scene, shape)
    shapes = {tuple(int(n) for n in s) for s in scene.image_shapes}
    for advice in sorted(filter(None, (crop_advice(s, shape) for s in shapes))):
        print(advice)
    if args.near is not None:
        near, far, where = args.near, args.far, "--near/--far"
    elif views.near is not None:
        near, far = views.near, views.far
        where = "from the sparse points; --near/--far to set it"
    else:
        near, far = near_far_from_sweep(
            [im.permute(1, 2, 0).numpy() for im in views.images[:2]],
            list(views.intrinsics[:2].double().numpy()),
            list(views.extrinsics[:2].double().numpy()))
        where = ("no sparse points: estimated by a plane sweep between the two context "
                 "views; --near/--far to set it")
    if posed:
        baseline = float((views.extrinsics[0, :3, 3] - views.extrinsics[1, :3, 3]).norm())
        where += (f"; COLMAP's scale is arbitrary: the context cameras are {baseline:.3g} "
                  "units apart")
    # the range matters (2-3 dB against the one a scene was trained with, docs/data.md): say it
    print(f"near/far {near:.4g} / {far:.4g} ({where})")
    # COLMAP's units are arbitrary: a range far from the trained one says nothing there
    warning = None if posed else depth_range_warning(near, far, trained_range)
    if warning:
        log.warning(warning)
    return views, near, far


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_example_arguments(p, data_required=False)
    add_own_views_arguments(p)
    p.add_argument("--path", default="orbit", help="the target cameras: 'orbit' (context 0 -> "
                   "1 -> 0, then a wobble around each) or a camera file like --cameras")
    p.add_argument("--frames", type=at_least(2), default=60,
                   help="frames of the orbit")
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
                                     budget=args.gaussians, rank_by=args.rank_by,
                                     tolerance=args.tolerance)
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
    cameras of a camera file."""
    if path == "orbit":
        e = camera_path(context_extrinsics.cpu(), frames).float()
        return e, context_intrinsics[:1].cpu().expand(len(e), 3, 3)
    return target_cameras(read_cameras(path, what="--path"), image_shape)


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
    if len(te) > MAX_PATH_CAMERAS:
        raise ValueError(f"--path {args.path} holds {len(te):,} cameras (at most "
                         f"{MAX_PATH_CAMERAS:,} frames): keep every k-th camera, or split the "
                         f"file and render the parts")
    return model.predict(views.images, intrinsics=views.intrinsics,
                         extrinsics=views.extrinsics, target_intrinsics=tk,
                         target_extrinsics=te, near=near, far=far, chunk=PATH_CHUNK,
                         budget=args.gaussians, rank_by=args.rank_by, all_gaussians=False,
                         tolerance=args.tolerance)


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
