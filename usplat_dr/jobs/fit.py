"""``usplat fit``: classic per-scene Gaussian optimisation with our rasteriser (a renderer check
on known geometry) on one synthetic scene, read from a ``usplat synth`` set or rendered on the
fly; writes a PNG of the held-out views and a JSON of the held-out PSNR/SSIM. The optimisation
is ``usplat_dr.training.per_scene``.
"""

import argparse
import json
from pathlib import Path

from usplat_dr.data.chunks import read_chunk, read_index
from usplat_dr.data.synth import render_spec, scene_record
from usplat_dr.data.synth.scenes import KINDS, make_spec
from usplat_dr.io import write_json
from usplat_dr.io.names import safe_stem
from usplat_dr.jobs.arguments import add_image_shape_option, at_least, out_folder, positive_int
from usplat_dr.training.per_scene import FitCfg, fit, views_from_record


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", help="a synthetic dataset root (usplat synth); without it a scene "
                   "is rendered on the fly from --kind/--seed/--frames/--image-shape")
    p.add_argument("--stage", default="test", help="stage folder of --data")
    p.add_argument("--scene", help="scene key in --data (default: the first)")
    p.add_argument("--kind", default="indoor", choices=KINDS,
                   help="the synthetic scene's kind")
    p.add_argument("--seed", type=int, default=0, help="the synthetic scene's seed")
    p.add_argument("--frames", type=at_least(4), default=24,
                   help="frames rendered (some held out: training.per_scene.split_views)")
    add_image_shape_option(p, [64, 64], "the rendered frames' size")
    p.add_argument("--spp", type=positive_int, default=256, help="Mitsuba samples per pixel")
    p.add_argument("--iterations", type=positive_int, default=1500,
                   help="Adam steps of the fit")
    p.add_argument("--out", type=out_folder, default="outputs/fit",
                   help="folder for the PNG and JSON")


def run(args: argparse.Namespace) -> int:
    if args.data:
        stage_dir = Path(args.data) / args.stage
        index = read_index(stage_dir)
        key = args.scene or next(iter(index))
        if key not in index:
            raise SystemExit(f"--scene {key!r} is not in {stage_dir / 'index.json'}")
        record = next(s for s in read_chunk(stage_dir / index[key]) if s["key"] == key)
    else:
        key = f"{args.kind}_{args.seed}"
        spec = make_spec(args.kind, args.seed, args.frames)
        images, depths, materials, k = render_spec(spec, tuple(args.image_shape), spp=args.spp,
                                                   seed=args.seed)
        record = scene_record(key, spec, images, depths, materials, k)
    out = Path(args.out)
    cfg = FitCfg(iterations=args.iterations, seed=args.seed)
    png = out / f"fit_{safe_stem(key)}.png"
    result = fit(views_from_record(record), cfg, out_png=png, progress=not args.quiet)
    write_json(png.with_suffix(".json"), {"scene": key, **result.__dict__})
    print(f"{key}: held-out PSNR {result.psnr_before:.2f} -> {result.psnr_after:.2f} dB, "
          f"SSIM {result.ssim_before:.3f} -> {result.ssim_after:.3f}, "
          f"{result.num_gaussians} Gaussians, {result.seconds:.0f} s "
          f"(renders: {png})")
    print(json.dumps({"psnr": round(result.psnr_after, 3)}))
    return 0
