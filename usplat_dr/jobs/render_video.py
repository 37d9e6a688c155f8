"""``usplat render``: a novel-view video of a scene along a camera path
(``usplat_dr.geometry.camera_paths``: context 0 -> 1 -> 0, then a wobble around each), colour
| depth. Every frame is a target view: UniqueSplat (c) predicts Gaussians per frame, in batches
of ``chunk`` frames.
"""

import argparse
from pathlib import Path

import numpy as np
import torch

from usplat_dr.data.types import model_inputs
from usplat_dr.evaluation import load_example, synthetic_indices
from usplat_dr.geometry.camera_paths import camera_path
from usplat_dr.io.images import colorize_depth
from usplat_dr.io.video import write_video
from usplat_dr.jobs.arguments import at_least, out_folder, positive_int
from usplat_dr.training.checkpoints import load_model, training_image_shape

DATASETS = ["synth", "re10k", "acid", "dtu"]


def add_example_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments naming a model and one evaluation example (``render``, ``export-ply``)."""
    p.add_argument("--checkpoint", required=True, help="usplat train's last.ckpt")
    p.add_argument("--data", required=True, help="dataset root (chunk format)")
    p.add_argument("--dataset", default="synth", choices=DATASETS)
    p.add_argument("--index", help="evaluation index JSON (default: the synthetic set's "
                   "standard split)")
    p.add_argument("--scene", help="scene key (default: the first of the index)")
    add_image_shape_argument(p)
    add_trust_argument(p)
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])


def add_trust_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--trust-checkpoint", action="store_true",
                   help="unpickle the checkpoint fully if torch.load(weights_only=True) refuses "
                   "it (it can run code: only for files you trust)")


def add_image_shape_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--image-shape", type=positive_int, nargs=2, metavar=("H", "W"),
                   help="the size images are cropped and resized to (default: the size the "
                   "checkpoint was trained at)")


def image_shape(args: argparse.Namespace) -> tuple[int, int]:
    """``--image-shape``, or the checkpoint's training image shape (the dataset preset's
    default, 256 x 256, for a checkpoint that records none)."""
    if args.image_shape:
        return tuple(args.image_shape)
    return training_image_shape(args.checkpoint, args.trust_checkpoint) or (256, 256)


def one_example(args: argparse.Namespace) -> tuple:
    """The model and the example that ``add_example_arguments``' arguments name."""
    index = args.index or synthetic_indices(args.data, ["standard"])["standard"]
    model, _ = load_model(args.checkpoint, args.device, args.trust_checkpoint)
    dataset = {"name": args.dataset, "roots": [args.data], "image_shape": image_shape(args)}
    return model, load_example(dataset, index, args.scene)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_example_arguments(p)
    p.add_argument("--frames", type=at_least(2), default=60)
    p.add_argument("--out", type=out_folder, default="outputs/render/video")


def run(args: argparse.Namespace) -> int:
    model, batch = one_example(args)
    colors, depths = render_path(model, batch, args.frames, device=args.device)
    valid = depths[np.isfinite(depths) & (depths > 0)]
    lo, hi = ((float(np.percentile(valid, 2)), float(np.percentile(valid, 98))) if valid.size
              else (1.0, 2.0))
    frames = np.concatenate([colors, np.stack([colorize_depth(d, near=lo, far=hi)
                                               for d in depths])], axis=2)
    path = write_video(frames, Path(args.out))
    print(f"wrote {path} ({len(frames)} frames: colour | depth)")
    return 0


@torch.no_grad()
def render_path(model, batch: dict, frames: int = 60, chunk: int = 8,
                device: torch.device | str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Colour [F, H, W, 3] and alpha-normalised depth [F, H, W] along ``camera_path``."""
    device = torch.device(device)
    inputs = model_inputs(batch, device)
    images, k, e = inputs.images, inputs.intrinsics, inputs.extrinsics  # the context views
    near, far = inputs.near, inputs.far
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
