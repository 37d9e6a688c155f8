"""``usplat view``: an interactive viewer in the browser (viser), where every camera the user
moves to is a target view: UniqueSplat predicts that view's own Gaussians and renders them.

The scene is a checkpoint with two context views, from a dataset (``--data``) or the user's own
images and camera file (``--images A B --cameras FILE``), or a 3DGS PLY (``--ply FILE``, drawn
by our rasteriser, no model). This module turns the arguments into a scene
(``scene_from_args``: ``usplat_dr.viewer.scene``'s ``ModelScene`` or ``PlyScene``) and serves
it (``start``: ``usplat_dr.viewer.server.Viewer``); ``--compare`` adds a second model, (a)
beside (c), switched in the page.
"""

import argparse
import logging
import math
import time
from pathlib import Path

import torch

from usplat_dr.data.types import model_inputs
from usplat_dr.jobs.arguments import (
    CHECKPOINT_HELP,
    DEVICE_HELP,
    add_image_shape_argument,
    add_own_views_arguments,
    add_scene_arguments,
    add_trust_argument,
    check_own_views,
    fit_checkpoint,
    one_example,
    own_views,
)
from usplat_dr.model.ply import read_ply
from usplat_dr.model.uniquesplat import VARIANTS
from usplat_dr.training.loader import load
from usplat_dr.training.registry import canonical_name, shipped_models
from usplat_dr.viewer.scene import PLY_IMAGE_SHAPE, VIEWER_HINT, ModelScene, PlyScene
from usplat_dr.viewer.server import Viewer, listening_port

log = logging.getLogger(__name__)

# ---- The command -------------------------------------------------------------------------

def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP)
    p.add_argument("--compare", metavar="CHECKPOINT",
                   help="a second model to switch to in the page, e.g. baseline-64 beside "
                   "full-64; 'none' for one model (default: with a shipped (c), the shipped "
                   "(a) trained nearest its size, else none)")
    add_scene_arguments(p.add_argument_group("context views from a dataset"))
    add_own_views_arguments(p)
    p.add_argument("--ply", help="a 3DGS PLY to look at instead of a model (rendered by our "
                   "rasteriser at --image-shape, default 256 256)")
    add_image_shape_argument(p)
    add_trust_argument(p)
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help=DEVICE_HELP)
    p.add_argument("--host", default="127.0.0.1",
                   help="address to serve on (0.0.0.0: every network interface)")
    p.add_argument("--port", type=int, default=8080,
                   help="port to serve on (the next free one if taken; 0: any)")


def compare_checkpoint(args: argparse.Namespace) -> str | None:
    """``--compare``, or its default: with a shipped user (c) (``--checkpoint``'s, after
    ``fit_checkpoint``), the shipped user (a) trained nearest its size; else none."""
    if args.compare is not None:
        return None if args.compare.lower() == "none" else args.compare
    models = shipped_models()
    name = canonical_name(args.checkpoint) if not Path(args.checkpoint).is_file() else None
    if name is None or models[name].kind != "user" or models[name].variant != "full":
        return None
    size = models[name].size or 64
    baselines = [m for m in models.values() if m.kind == "user" and m.variant == "baseline"
                 and m.size]
    if not baselines:
        return None
    return min(baselines, key=lambda m: (abs(math.log2(m.size / size)), -m.size)).name


def label(model, checkpoint: str) -> str:
    """"(c) UniqueSplat: full-64": the model's variant and where it came from (a shipped
    model's name, or a file's name)."""
    shipped = not Path(checkpoint).is_file() and canonical_name(checkpoint) is not None
    return f"{VARIANTS[model.cfg.variant]}: {checkpoint if shipped else Path(checkpoint).name}"


def check_arguments(args: argparse.Namespace) -> None:
    """The mistakes that need no file read: one scene source, and what goes with it."""
    if not 0 <= args.port <= 65535:
        raise ValueError(f"--port must be in 0..65535, got {args.port}")
    if args.ply is not None:
        if args.checkpoint or args.data or args.images:
            raise ValueError("give --ply FILE alone, or --data or --images (with a model: "
                             "--checkpoint, default the shipped (c)); a PLY is drawn without "
                             "a model")
        return
    if (args.data is None) == (args.images is None):
        raise ValueError("give --data (a dataset in the chunk format) or --images A B "
                         "--cameras FILE (your own images), one of them")
    if args.images is not None:
        check_own_views(args)


def scene_from_args(args: argparse.Namespace):
    """The ``ModelScene`` or ``PlyScene`` that the arguments name."""
    check_arguments(args)
    if args.ply is not None:
        return PlyScene(read_ply(args.ply), tuple(args.image_shape or PLY_IMAGE_SHAPE),
                        f"PLY: {Path(args.ply).name}")
    fit_checkpoint(args)
    compare = compare_checkpoint(args)
    if args.data is not None:
        model, batch = one_example(args)
        inputs = model_inputs(batch, torch.device(args.device))
        images, e, k = inputs.images[0], inputs.extrinsics[0], inputs.intrinsics[0]
        near, far = float(inputs.near[0].min()), float(inputs.far[0].max())
    else:
        model = load(args.checkpoint, args.device, args.trust_checkpoint)
        views, near, far = own_views(args, model.trained_depth_range)
        images, e, k = views.images, views.extrinsics, views.intrinsics
    models = {label(model, args.checkpoint): model}
    if compare is not None:
        other = load(compare, args.device, args.trust_checkpoint)
        models[label(other, compare)] = other
    return ModelScene(models, images.cpu(), e.cpu(), k.cpu(), float(near), float(far))


def start(args: argparse.Namespace) -> Viewer:
    """The viewer of the arguments, serving (its own threads); ``stop()`` ends it."""
    check_arguments(args)
    try:
        import viser  # noqa: F401  (before the seconds of loading a model)
    except ImportError:
        raise ValueError(VIEWER_HINT) from None
    # an address not here: one line before a model loads; a taken port said once
    args.port = listening_port(args.host, args.port)
    return Viewer(scene_from_args(args), args.host, args.port)


def run(args: argparse.Namespace) -> int:
    viewer = start(args)
    print(f"usplat view: open {viewer.url} in a browser (Ctrl+C stops)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
    return 0

