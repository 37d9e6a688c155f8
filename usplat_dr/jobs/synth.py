"""``usplat synth``: render procedural scenes with known geometry (Mitsuba) into the field's
chunk format, with evaluation and stress splits."""

import argparse
import os
import time
from pathlib import Path

from usplat_dr.data.synth import synthesize
from usplat_dr.data.synth.scenes import APPEARANCES, KINDS
from usplat_dr.jobs.arguments import (
    add_image_shape_option,
    at_least,
    non_negative_int,
    out_folder,
    positive_int,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=out_folder, required=True,
                   help="dataset root to write (<out>/<stage>/*.torch); the test stage's "
                   "evaluation indices, splits.json, synth.json and previews/ go into <out>, "
                   "the train stage's into <out>/train/")
    p.add_argument("--scenes", type=positive_int, default=32, help="number of scenes")
    p.add_argument("--frames", type=at_least(3), default=24, help="frames per scene (>= 3)")
    add_image_shape_option(p, [64, 64], "image height and width")
    p.add_argument("--seed", type=int, default=None,
                   help="same seed, same bytes (whatever the stage). Default: 0 for --stage "
                   "test, 1 for --stage train, so that a train and a test set made without "
                   "--seed share no scene; a stage whose scenes the other stage of --out "
                   "already holds is refused")
    p.add_argument("--kind", nargs="+", default=list(KINDS), choices=KINDS,
                   help="scene kinds, used round-robin")
    p.add_argument("--appearance", default="diffuse", choices=APPEARANCES,
                   help="diffuse: mostly matte surfaces, direct lighting under a constant sky; "
                   "view-dependent: the same geometry with at least half of the surfaces "
                   "glossy or metallic (floors always), a structured sky and path tracing, "
                   "so that appearance changes with the viewpoint (near-mirror surfaces); "
                   "rough-glossy: the same surfaces rough (GGX 0.15-0.4): broad highlights "
                   "that move smoothly with the viewpoint")
    p.add_argument("--spp", type=positive_int, default=None,
                   help="Mitsuba samples per pixel (default: 64 diffuse, 256 view-dependent "
                   "and rough-glossy: "
                   "path tracing's noise on shiny surfaces needs it)")
    p.add_argument("--backend", default="llvm", choices=["llvm", "cuda"],
                   help="Mitsuba variant: llvm_ad_rgb (CPU) or cuda_ad_rgb")
    p.add_argument("--stage", default="test", choices=["train", "test"],
                   help="stage folder to write")
    p.add_argument("--previews", type=non_negative_int, default=8,
                   help="scenes to write preview PNGs for")
    p.add_argument("--chunk-scenes", type=positive_int, default=None, metavar="N",
                   help="at most N scenes per chunk file (default: chunks of up to 100 MB). "
                   "Training shards by scene, so any number of chunks trains on any number "
                   "of ranks; smaller chunks let each DataLoader worker read less")
    p.add_argument("--jobs", type=non_negative_int, default=0,
                   help="worker processes rendering scenes in parallel (0: one per core, at "
                   "most one per 4 scenes; the bytes written do not depend on it)")


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    summary = synthesize(Path(args.out), scenes=args.scenes, frames=args.frames,
                         resolution=tuple(args.image_shape), seed=args.seed,
                         kinds=tuple(args.kind), spp=args.spp, backend=args.backend,
                         stage=args.stage, previews=args.previews, progress=not args.quiet,
                         jobs=args.jobs or min(os.cpu_count() or 1, max(1, args.scenes // 4)),
                         chunk_scenes=args.chunk_scenes, appearance=args.appearance)
    dt = time.perf_counter() - t0
    print(f"wrote {args.scenes} scenes x {args.frames} frames to {args.out} in {dt:.1f} s "
          f"({60 * args.scenes / dt:.1f} scenes/min)")
    print("scenes per evaluation split: " + ", ".join(f"{k} {v}" for k, v in summary.items()))
    return 0
