"""``usplat import``: a COLMAP sparse model or a nerfstudio transforms.json (and its images)
into the field's chunk format, with a standard evaluation index (docs/data.md, "Importing
your own scenes")."""

import argparse
import json
from pathlib import Path

from usplat_dr.data.importers import import_scene, read_colmap, read_nerfstudio
from usplat_dr.jobs.arguments import (
    add_image_shape_option,
    non_negative_int,
    out_folder,
    positive_float,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--colmap", metavar="DIR",
                        help="COLMAP sparse model folder (cameras/images/points3D .bin or "
                        ".txt), or a project folder holding sparse/0")
    source.add_argument("--nerfstudio", metavar="DIR", help="folder holding transforms.json")
    p.add_argument("--images", metavar="DIR", default=None,
                   help="COLMAP only: the images folder (default: images/ beside the model, "
                   "one or two folders up)")
    p.add_argument("--out", type=out_folder, required=True,
                   help="dataset root to write (<out>/<stage>/000000.torch, index.json, "
                   "<out>/evaluation_index_standard.json)")
    p.add_argument("--stage", default="test", choices=["train", "test"],
                   help="stage folder to write")
    add_image_shape_option(p, None, "resize every image to H x W (default: keep the size)")
    p.add_argument("--key", default=None, help="scene key (default: the source folder's name)")
    p.add_argument("--context", type=non_negative_int, nargs=2, default=None,
                   metavar=("I", "J"), help="context frames of the evaluation index (frames "
                   "ordered by image name; default: V/3 apart, centred)")
    p.add_argument("--near", type=positive_float, default=None,
                   help="near plane (scene units; default: from the sparse points)")
    p.add_argument("--far", type=positive_float, default=None, help="far plane (with --near)")
    p.add_argument("--format", default="png", choices=["png", "jpeg"],
                   help="image encoding in the chunk (png: lossless; jpeg: the field's)")
    p.add_argument("--ignore-distortion", action="store_true",
                   help="drop SIMPLE_RADIAL/RADIAL/OPENCV distortion with a warning instead of "
                   "refusing the model (small distortion only; undistort wide lenses first)")


def run(args: argparse.Namespace) -> int:
    if args.colmap is not None:
        scene = read_colmap(Path(args.colmap), args.images, args.ignore_distortion)
    else:
        if args.images is not None:
            raise ValueError("--images is for --colmap; transforms.json names its image files")
        scene = read_nerfstudio(Path(args.nerfstudio), args.ignore_distortion)
    summary = import_scene(scene, args.out, stage=args.stage,
                           resolution=tuple(args.image_shape) if args.image_shape else None,
                           key=args.key, context=tuple(args.context) if args.context else None,
                           near=args.near, far=args.far, fmt=args.format)
    if not args.quiet:
        print(json.dumps(summary, indent=1))
    print(f"imported {summary['views']} views of {summary['key']!r} "
          f"({summary['image_shape'][0]}x{summary['image_shape'][1]}, near/far "
          f"{summary['near_far'][0]:.4g}/{summary['near_far'][1]:.4g}) into {args.out}")
    return 0
