"""The ``usplat`` command line."""

import argparse
import json
import logging
import os
import sys
from pathlib import Path


def _render_demo(args) -> int:
    from usplat_dr.demo import render_demo

    paths = render_demo(Path(args.out), size=args.size, views=args.views, device=args.device)
    print(f"wrote {len(paths)} images to {args.out} (overview: {paths[-1]})")
    return 0


def _synth(args) -> int:
    import time

    from usplat_dr.data.synth import synthesize

    t0 = time.perf_counter()
    summary = synthesize(Path(args.out), scenes=args.scenes, frames=args.frames,
                         resolution=tuple(args.resolution), seed=args.seed,
                         kinds=tuple(args.kind), spp=args.spp, backend=args.backend,
                         stage=args.stage, previews=args.previews, progress=not args.quiet,
                         jobs=args.jobs or min(os.cpu_count() or 1, max(1, args.scenes // 4)))
    dt = time.perf_counter() - t0
    print(f"wrote {args.scenes} scenes x {args.frames} frames to {args.out} in {dt:.1f} s "
          f"({60 * args.scenes / dt:.1f} scenes/min)")
    print("scenes per evaluation split: " + ", ".join(f"{k} {v}" for k, v in summary.items()))
    return 0


def _fit(args) -> int:
    import json

    from usplat_dr.fit import FitCfg, fit, views_from_record

    if args.data:
        from usplat_dr.data.chunks import read_chunk, read_index

        stage_dir = Path(args.data) / args.stage
        index = read_index(stage_dir)
        key = args.scene or next(iter(index))
        if key not in index:
            raise SystemExit(f"--scene {key!r} is not in {stage_dir / 'index.json'}")
        record = next(s for s in read_chunk(stage_dir / index[key]) if s["key"] == key)
    else:
        from usplat_dr.data.synth import render_spec, scene_record
        from usplat_dr.data.synth.scenes import make_spec

        key = f"{args.kind}_{args.seed}"
        spec = make_spec(args.kind, args.seed, args.frames)
        images, depths, materials, k = render_spec(spec, tuple(args.resolution), spp=args.spp,
                                                   seed=args.seed)
        record = scene_record(key, spec, images, depths, materials, k)
    out = Path(args.out)
    cfg = FitCfg(iterations=args.iterations, seed=args.seed)
    result = fit(views_from_record(record), cfg, out_png=out / f"fit_{key}.png",
                 progress=not args.quiet)
    summary = {"scene": key, **result.__dict__}
    from usplat_dr.io import write_json

    write_json(out / f"fit_{key}.json", summary)
    print(f"{key}: held-out PSNR {result.psnr_before:.2f} -> {result.psnr_after:.2f} dB, "
          f"SSIM {result.ssim_before:.3f} -> {result.ssim_after:.3f}, "
          f"{result.num_gaussians} Gaussians, {result.seconds:.0f} s "
          f"(renders: {out / f'fit_{key}.png'})")
    print(json.dumps({"psnr": round(result.psnr_after, 3)}))
    return 0


def _params(args) -> int:
    from usplat_dr.model.uniquesplat import PAPER_PARAMETERS, UniqueSplat

    logging.getLogger("usplat_dr.model.hypernet.resnet").setLevel(logging.ERROR)
    variants = ["baseline", "agnostic", "full"] if args.variant == "all" else [args.variant]
    for variant in variants:
        model = UniqueSplat.from_preset(args.preset, variant=variant)
        print(f"preset {args.preset!r}, variant {variant!r}")
        for name, count in model.parameter_table():
            print(f"  {name:<62} {count:>12,}")
        total = model.parameter_table()[-1][1]
        if args.preset == "paper" and variant == "full":
            print(f"  {'paper (UniqueSplat, full model)':<62} {PAPER_PARAMETERS:>12,.0f}"
                  f"  ({100 * (total / PAPER_PARAMETERS - 1):+.1f}%)")
    return 0


def _train(args) -> int:
    from usplat_dr.config import load_config
    from usplat_dr.training import train

    cfg = load_config(args.config or ["synthetic_tiny.yaml"], args.overrides)
    result = train(cfg, resume=args.resume)
    print(json.dumps(result))
    return 0


def _eval(args) -> int:
    from usplat_dr.evaluation import evaluate, load_model, synthetic_indices

    indices = dict(item.split("=", 1) for item in args.index) if args.index else None
    if indices is None:
        indices = synthetic_indices(args.data, args.splits)
        if not indices:
            print(f"no evaluation_index_*.json with scenes in {args.data}; pass --index "
                  f"NAME=PATH (e.g. standard=assets/evaluation_index_re10k.json)")
            return 2
    lpips = None
    if args.lpips_vgg or args.lpips_lin:
        from usplat_dr.lpips import LPIPS

        lpips = LPIPS.from_files(args.lpips_vgg, args.lpips_lin).to(args.device)
    model, step = load_model(args.checkpoint, args.device)
    dataset = {"name": args.dataset, "roots": [args.data], "image_shape": args.image_shape}
    summary = evaluate(model, dataset, indices, args.out, lpips=lpips, device=args.device)
    print(json.dumps(summary, indent=1))
    return 0


def _one_example(args):
    from usplat_dr.evaluation import load_example, load_model, synthetic_indices

    index = args.index or synthetic_indices(args.data, ["standard"])["standard"]
    dataset = {"name": args.dataset, "roots": [args.data], "image_shape": args.image_shape}
    model, _ = load_model(args.checkpoint, args.device)
    return model, load_example(dataset, index, args.scene)


def _render(args) -> int:
    import numpy as np

    from usplat_dr.images import colorize_depth
    from usplat_dr.video import render_path, write_video

    model, batch = _one_example(args)
    colors, depths = render_path(model, batch, args.frames, device=args.device)
    valid = depths[np.isfinite(depths) & (depths > 0)]
    lo, hi = ((float(np.percentile(valid, 2)), float(np.percentile(valid, 98))) if valid.size
              else (1.0, 2.0))
    frames = np.concatenate([colors, np.stack([colorize_depth(d, near=lo, far=hi)
                                               for d in depths])], axis=2)
    path = write_video(frames, Path(args.out))
    print(f"wrote {path} ({len(frames)} frames: colour | depth)")
    return 0


def _export_ply(args) -> int:
    import torch

    from usplat_dr.ply import write_ply
    from usplat_dr.training import scene_args

    model, batch = _one_example(args)
    with torch.no_grad():
        out = model(*scene_args(batch, torch.device(args.device)), render=False)
    n = out.num_targets
    if not 0 <= args.target < n:
        print(f"--target must be in 0..{n - 1} (the scene's target views)")
        return 2
    path = write_ply(args.out, out.target(0, args.target), min_opacity=args.min_opacity)
    print(f"wrote {path}: the Gaussians predicted for target {args.target} of "
          f"{batch['scene'][0]}")
    return 0


def _demo(args) -> int:
    from usplat_dr.demo_job import run_demo

    run_demo(args.out, "quick" if args.quick else "full", jobs=args.jobs)
    return 0


def _bench(args) -> int:
    from usplat_dr.bench_job import DEFAULT_CONFIGS, PRUNES, BenchConfig, run_bench

    configs = ([BenchConfig.parse(c) for c in args.configs.split(",")] if args.configs
               else DEFAULT_CONFIGS)
    prunes = PRUNES
    if args.prunes:
        unknown = set(args.prunes.split(",")) - set(PRUNES)
        if unknown:
            raise SystemExit(f"--prunes: unknown {sorted(unknown)}; choose from {list(PRUNES)}")
        prunes = {k: PRUNES[k] for k in args.prunes.split(",")}
    sizes = [int(s) for s in args.render_sizes.split(",")] if args.render_sizes else None
    run_bench(args.out, "quick" if args.quick else "full", configs, sizes, prunes,
              device=args.device, jobs=args.jobs)
    return 0


def _doctor(args) -> int:
    from usplat_dr import doctor

    return doctor.run()


def main(argv: list[str] | None = None) -> int:
    from usplat_dr import portable

    # Same numbers from the same command on every AVX2 CPU (before torch is imported).
    portable.enable()
    parser = argparse.ArgumentParser(prog="usplat", description="usplat-dr: UniqueSplat with a "
                                     "Dr.Jit Gaussian rasteriser")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("doctor", help="report versions, libLLVM, backends, GPU; exit 1 on "
                       "problems")
    p.set_defaults(func=_doctor)

    p = sub.add_parser("render-demo", help="render a procedural Gaussian scene from several "
                       "cameras to PNGs")
    p.add_argument("--out", default="outputs/render-demo", help="output folder")
    p.add_argument("--size", type=int, default=256, help="image height and width in pixels")
    p.add_argument("--views", type=int, default=6, help="number of cameras on the orbit")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                   help="cpu: Dr.Jit LLVM backend; cuda: Dr.Jit CUDA backend")
    p.set_defaults(func=_render_demo)

    p = sub.add_parser("params", help="parameter count of a UniqueSplat configuration, per "
                       "part")
    p.add_argument("--preset", default="paper", choices=["paper", "small", "tiny"])
    p.add_argument("--variant", default="all", choices=["all", "baseline", "agnostic", "full"])
    p.set_defaults(func=_params)

    p = sub.add_parser("train", help="train UniqueSplat (any variant) with the field's recipe; "
                       "also under torchrun (DistributedDataParallel)")
    p.add_argument("--config", action="append",
                   help="a YAML file's path, or a packaged config's name (usplat_dr/configs/: "
                   "synthetic_tiny.yaml, synthetic_tiny_depth.yaml, ...); repeat to merge "
                   "several in order (default: synthetic_tiny.yaml)")
    p.add_argument("--resume", action="store_true",
                   help="continue from output_dir/checkpoints/last.ckpt when it exists")
    p.add_argument("overrides", nargs="*", metavar="key.sub=value",
                   help="dotted overrides, e.g. optimizer.lr=1e-4 train.steps=100")
    p.set_defaults(func=_train)

    p = sub.add_parser("eval", help="evaluate a trained model with the field's protocol "
                       "(per-scene CSV, summary JSON, renders)")
    p.add_argument("--checkpoint", required=True, help="usplat train's last.ckpt")
    p.add_argument("--data", required=True, help="dataset root (chunk format)")
    p.add_argument("--dataset", default="synth", choices=["synth", "re10k", "acid", "dtu"])
    p.add_argument("--index", nargs="+", metavar="SPLIT=PATH",
                   help="evaluation index JSON(s); default: the synthetic set's own splits")
    p.add_argument("--splits", nargs="+", help="synthetic splits to evaluate (default: all)")
    p.add_argument("--image-shape", type=int, nargs=2, default=[256, 256], metavar=("H", "W"))
    p.add_argument("--lpips-vgg", help="torchvision vgg16-397923af.pth (for LPIPS)")
    p.add_argument("--lpips-lin", help="lpips/weights/v0.1/vgg.pth (for LPIPS)")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--out", default="outputs/eval")
    p.set_defaults(func=_eval)

    for name, func, helptext in (
            ("render", _render, "a video (mp4 with ffmpeg, else GIF) along a path between the "
             "context views and a wobble around them"),
            ("export-ply", _export_ply, "the Gaussians predicted for one target view, as a "
             "standard 3DGS PLY")):
        p = sub.add_parser(name, help=helptext)
        p.add_argument("--checkpoint", required=True, help="usplat train's last.ckpt")
        p.add_argument("--data", required=True, help="dataset root (chunk format)")
        p.add_argument("--dataset", default="synth", choices=["synth", "re10k", "acid", "dtu"])
        p.add_argument("--index", help="evaluation index JSON (default: the synthetic set's "
                       "standard split)")
        p.add_argument("--scene", help="scene key (default: the first of the index)")
        p.add_argument("--image-shape", type=int, nargs=2, default=[256, 256],
                       metavar=("H", "W"))
        p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
        if name == "render":
            p.add_argument("--frames", type=int, default=60)
            p.add_argument("--out", default="outputs/render/video")
        else:
            p.add_argument("--target", type=int, default=0, help="target view index")
            p.add_argument("--min-opacity", type=float, default=0.0)
            p.add_argument("--out", default="outputs/export/gaussians.ply")
        p.set_defaults(func=func)

    p = sub.add_parser("demo", help="the main job: synthetic data, train (a) and (c), "
                       "evaluate, write a report (about 15 minutes on 2 CPU cores)")
    p.add_argument("--out", default="outputs/demo")
    p.add_argument("--quick", action="store_true", help="a tiny budget (CI): a minute or two")
    p.add_argument("--jobs", type=int, default=0, help="Mitsuba worker processes (0: auto)")
    p.set_defaults(func=_demo)

    p = sub.add_parser("bench", help="speed against accuracy: train (or reuse) size presets "
                       "x variants on the demo's data, measure time per view, memory, "
                       "Gaussians and accuracy; CSV + chart in OUT/bench")
    p.add_argument("--out", default="outputs/demo", help="the demo folder (its data and runs "
                   "are shared)")
    p.add_argument("--configs", default="", help="comma-separated preset:variant, e.g. "
                   "tiny:a,tiny:c,small:c (default: tiny a/b/c, small c, paper c)")
    p.add_argument("--prunes", default="", help="comma-separated pruning settings (default: "
                   "all, cull, cull+merge1px, cull+merge2px, keep50%%, keep25%%)")
    p.add_argument("--render-sizes", default="", help="comma-separated render sizes <= the "
                   "data's (default: half and full)")
    p.add_argument("--quick", action="store_true", help="the demo's quick budget (CI)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--jobs", type=int, default=0, help="Mitsuba worker processes (0: auto)")
    p.set_defaults(func=_bench)

    from usplat_dr.data.synth.scenes import KINDS

    p = sub.add_parser("synth", help="render procedural scenes with known geometry (Mitsuba) "
                       "into the field's chunk format, with evaluation and stress splits")
    p.add_argument("--out", required=True, help="dataset root to write (<out>/<stage>/*.torch)")
    p.add_argument("--scenes", type=int, default=32, help="number of scenes")
    p.add_argument("--frames", type=int, default=24, help="frames per scene (>= 3)")
    p.add_argument("--resolution", type=int, nargs=2, default=[64, 64], metavar=("H", "W"),
                   help="image height and width")
    p.add_argument("--seed", type=int, default=0, help="same seed, same bytes")
    p.add_argument("--kind", nargs="+", default=list(KINDS), choices=KINDS,
                   help="scene kinds, used round-robin")
    p.add_argument("--spp", type=int, default=64, help="Mitsuba samples per pixel")
    p.add_argument("--backend", default="llvm", choices=["llvm", "cuda"],
                   help="Mitsuba variant: llvm_ad_rgb (CPU) or cuda_ad_rgb")
    p.add_argument("--stage", default="test", choices=["train", "test"],
                   help="stage folder to write")
    p.add_argument("--previews", type=int, default=8, help="scenes to write preview PNGs for")
    p.add_argument("--jobs", type=int, default=0,
                   help="worker processes rendering scenes in parallel (0: one per core, at "
                   "most one per 4 scenes; the bytes written do not depend on it)")
    p.set_defaults(func=_synth)

    p = sub.add_parser("fit", help="per-scene Gaussian optimisation on a synthetic scene "
                       "(renderer check): held-out PSNR/SSIM and a PNG of renders")
    p.add_argument("--data", help="a synthetic dataset root (usplat synth); without it a scene "
                   "is rendered on the fly from --kind/--seed/--frames/--resolution")
    p.add_argument("--stage", default="test", help="stage folder of --data")
    p.add_argument("--scene", help="scene key in --data (default: the first)")
    p.add_argument("--kind", default="indoor", choices=KINDS)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--frames", type=int, default=24)
    p.add_argument("--resolution", type=int, nargs=2, default=[64, 64], metavar=("H", "W"))
    p.add_argument("--spp", type=int, default=256, help="Mitsuba samples per pixel")
    p.add_argument("--iterations", type=int, default=1500)
    p.add_argument("--out", default="outputs/fit", help="folder for the PNG and JSON")
    p.set_defaults(func=_fit)

    args = parser.parse_args(argv)
    if getattr(args, "size", 1) < 1 or getattr(args, "views", 1) < 1:
        parser.error("--size and --views must be >= 1")
    if args.command == "fit" and (args.iterations < 1 or args.frames < 4):
        parser.error("--iterations must be >= 1 and --frames >= 4")
    if args.command == "synth":
        if args.scenes < 1 or args.frames < 3:
            parser.error("--scenes must be >= 1 and --frames >= 3")
        if min(args.resolution) < 4 or args.spp < 1 or args.jobs < 0:
            parser.error("--resolution must be at least 4 4, --spp >= 1 and --jobs >= 0")
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO,
                        format="%(message)s")
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
