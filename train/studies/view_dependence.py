"""The view-dependence meter of a synthetic set: every context view warped into every target
with the true depths, PSNR of warped against true on the co-visible pixels, per material class
(``usplat_dr.evaluation.view_dependence``). Diffuse pixels sit at the resampling and noise
floor; glossy and metallic ones fall below it by as much as their appearance changes with the
viewpoint.

    python train/studies/view_dependence.py --data outputs/big/vd_test2000 --split standard \
        --out outputs/meter/vd_test2000 [--noise-floor 12]

Writes ``<out>/meter.json`` (per scene and per class) and ``<out>/images/<scene>.png`` (target,
warped context, |difference| x4, material map: grey matte, blue glossy, orange metal).
"""

import argparse
import json
import sys
from pathlib import Path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="a `usplat synth` set")
    p.add_argument("--split", default="standard", help="its evaluation index to use")
    p.add_argument("--stage", default="test")
    p.add_argument("--out", required=True)
    p.add_argument("--images", type=int, default=6, help="scenes to write error images for")
    p.add_argument("--noise-floor", type=int, default=0, metavar="N",
                   help="also render the first target of N scenes again with another sample "
                        "seed: the render noise per class, the ceiling of a warp's PSNR")
    args = p.parse_args(argv)
    from usplat_dr.data.synth import metadata_folder
    from usplat_dr.evaluation import synthetic_indices
    from usplat_dr.evaluation.view_dependence import (
        meter,
        noise_floor,
        paired_gap,
        write_error_images,
    )
    from usplat_dr.io import write_json

    # The stage's own indices and synth.json (the train stage's are in <data>/train/; sets
    # made before per-stage metadata have only the root's)
    meta = metadata_folder(args.data, args.stage)
    if not (meta / "synth.json").is_file():
        meta = Path(args.data)
    index = json.loads(Path(synthetic_indices(meta, [args.split])[args.split]).read_text())
    result = meter(args.data, index, args.stage)
    gaps = {name: paired_gap(result, name) for name in ("glossy", "metal")}
    out = Path(args.out)
    noise = {}
    if args.noise_floor:
        spp = json.loads((meta / "synth.json").read_text())["spp"]
        noise = noise_floor(args.data, index, args.noise_floor, spp, args.stage)
    write_json(out / "meter.json", {"data": args.data, "split": args.split,
                                    "classes": result["classes"], "diffuse_minus": gaps,
                                    "noise_floor": noise, "scenes": result["scenes"]})
    write_error_images(args.data, index, out / "images", args.images, args.stage)
    print(f"warp PSNR on co-visible pixels, {args.data} ({args.split}, "
          f"{len(result['scenes'])} scenes)")
    print("| class | mean over scenes (dB) | scenes | pooled (dB) | pixels |")
    print("|---|---|---|---|---|")
    for name, c in result["classes"].items():
        print(f"| {name} | {c['psnr']:.2f} | {c['scenes']} | {c['pooled_psnr']:.2f} | "
              f"{c['pixels']} |")
    for name, c in noise.items():
        print(f"render noise floor, {name}: {c['psnr']:.2f} dB over {c['pixels']} pixels "
              f"({args.noise_floor} scenes)")
    for name, g in gaps.items():
        print(f"diffuse - {name}, paired by scene: {g['mean']:+.2f} dB over {g['scenes']} scenes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
