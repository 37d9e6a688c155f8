"""The ``usplat`` command line."""

import argparse
import logging
import sys
from pathlib import Path


def _render_demo(args) -> int:
    from usplat_dr.demo import render_demo

    paths = render_demo(Path(args.out), size=args.size, views=args.views, device=args.device)
    print(f"wrote {len(paths)} images to {args.out} (overview: {paths[-1]})")
    return 0


def _doctor(args) -> int:
    from usplat_dr import doctor

    return doctor.run()


def main(argv: list[str] | None = None) -> int:
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

    args = parser.parse_args(argv)
    if getattr(args, "size", 1) < 1 or getattr(args, "views", 1) < 1:
        parser.error("--size and --views must be >= 1")
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO,
                        format="%(message)s")
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
