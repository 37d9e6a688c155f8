"""``usplat pose``: photos without cameras posed by COLMAP (pycolmap) into a COLMAP model
folder that ``import``, ``render --cameras`` and ``view`` read as they are
(``usplat_dr.data.pose``)."""

import argparse
import logging
from pathlib import Path

from usplat_dr import _threads
from usplat_dr.data.pose import PoseSettings, photos_in, pose_photos
from usplat_dr.jobs.arguments import at_least, out_folder

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("photos", nargs="*", metavar="PHOTO", help="the photos (PNG or JPEG)")
    p.add_argument("--images", metavar="DIR", help="a folder of photos (its .jpg, .jpeg and "
                   ".png files) instead of, or besides, PHOTO...")
    p.add_argument("--out", type=out_folder, required=True,
                   help="the folder to write: images/ (undistorted), sparse/ (the COLMAP "
                   "model, a PINHOLE camera), distorted/ (database and raw model), pose.json")
    p.add_argument("--matching", default="auto", choices=["auto", "exhaustive", "sequential"],
                   help="feature matching: every pair, or each photo with its neighbours in "
                   "name order (video frames); auto: exhaustive up to 100 photos")
    p.add_argument("--camera", default="auto", choices=["auto", "single", "per-image"],
                   help="one camera for every photo, or one each; auto: single when the photos "
                   "share a size and their EXIF names one camera or none")
    p.add_argument("--max-image-size", type=at_least(64), default=1600,
                   help="the long side, in pixels, SIFT extracts features at")
    p.add_argument("--seed", type=int, default=0, help="COLMAP's random seed")


def run(args: argparse.Namespace) -> int:
    photos = [Path(p) for p in args.photos]
    if args.images:
        photos += photos_in(Path(args.images))
    if not photos:
        raise ValueError("give the photos (usplat pose A.jpg B.jpg ...) or --images DIR")
    settings = PoseSettings(matching=args.matching, camera=args.camera,
                            max_image_size=args.max_image_size, seed=args.seed,
                            threads=_threads.choose().threads)
    result = pose_photos(photos, args.out, settings, progress=not args.quiet)
    print(result.line())
    print(f"next: usplat render --cameras {result.model} --images "
          f"{result.images / result.registered[0]} {result.images / result.registered[1]} "
          f"--out outputs/render/posed")
    return 0
