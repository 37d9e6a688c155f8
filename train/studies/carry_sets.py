"""Synthetic sets made small enough to travel to a machine without Mitsuba (a GPU machine
whose working tree may hold about 60 MB in all), and unpacked there.

    python train/studies/carry_sets.py pack --out .gpudata \\
        train=outputs/big/train480/train:150:jpeg heldout=outputs/big/test5000:30:png
    python train/studies/carry_sets.py unpack .gpudata          # on the other machine

``pack`` writes, per set NAME=FOLDER[:SCENES[:IMAGES]], the first SCENES scenes of FOLDER's
chunks (a ``usplat synth`` test root or a train stage's folder) as one ``NAME/000000.torch.xz``
(under ``NAME/test/`` for a test root, ``NAME/train/`` for a train stage) plus FOLDER's
``evaluation_index_*.json``: images re-encoded as JPEG (``--jpeg-quality``, ``--chroma``;
default quality 95 without chroma subsampling, 39 dB against the PNG at 64x64, see
``JPEG_QUALITY``) or kept as they are (``png``), depths kept, material maps and Mitsuba
descriptions dropped (nothing trains or scores with them). At 64x64 a scene of 24 frames is
then about 120 KB (89 KB of JPEG, 30 KB of xz-compressed float16 depth; 66 KB with quality
90 and 4:2:0 chroma) against 450 KB as rendered. ``unpack`` decompresses every
``*.torch.xz`` under a folder in place, so each set's folder is a dataset root (``--sets`` and
``dataset.roots`` take it as rendered sets are taken).
"""

import argparse
import io
import lzma
import shutil
import sys
from pathlib import Path

import torch
from PIL import Image

import usplat_dr  # noqa: F401  (libLLVM first)
from usplat_dr.data.chunks import write_index

#: JPEG's quality and chroma subsampling by default. Measured on 120 images of the 64x64
#: training set (2026-11-27), PSNR of the JPEG against the rendered PNG and its bytes against
#: the PNG's: quality 90 with 4:2:0 chroma 30.9 dB (min 25.1), 0.32x; quality 90, 4:4:4 35.3
#: dB, 0.42x; quality 95, 4:4:4 39.2 dB (min 37.1), 0.57x; quality 98, 4:4:4 44.9 dB, 0.80x.
#: Halved chroma costs the most at 64x64, where a model itself renders about 30 dB.
JPEG_QUALITY, CHROMA = 95, "444"
SUBSAMPLING = {"444": 0, "422": 1, "420": 2}  # PIL's subsampling codes


def scenes_of(folder: Path, count: int | None):
    """The first ``count`` scenes (all with None) of the chunk files in ``folder``
    (``folder/test`` when it is a test root), in file and chunk order."""
    stage = folder / "test" if (folder / "test").is_dir() else folder
    taken = 0
    for chunk in sorted(stage.glob("*.torch")):
        for scene in torch.load(chunk, weights_only=False):
            if count is not None and taken == count:
                return
            taken += 1
            yield scene


def as_jpeg(encoded: torch.Tensor, quality: int = JPEG_QUALITY, chroma: str = CHROMA
            ) -> torch.Tensor:
    """One encoded image (uint8 bytes) re-encoded as JPEG."""
    image = Image.open(io.BytesIO(encoded.numpy().tobytes())).convert("RGB")
    out = io.BytesIO()
    image.save(out, format="JPEG", quality=quality, subsampling=SUBSAMPLING[chroma])
    return torch.frombuffer(bytearray(out.getvalue()), dtype=torch.uint8)


def slim(scene: dict, images: str, quality: int = JPEG_QUALITY, chroma: str = CHROMA) -> dict:
    keep = {k: v for k, v in scene.items() if k not in ("materials", "mitsuba")}
    if images == "jpeg":
        keep["images"] = [as_jpeg(im, quality, chroma) for im in scene["images"]]
    return keep


def pack(sets: list[str], out: Path, quality: int = JPEG_QUALITY, chroma: str = CHROMA
         ) -> None:
    for item in sets:
        name, _, spec = item.partition("=")
        folder, count, images = (spec.split(":") + [None, None])[:3]
        images = images or "jpeg"
        if not name or not folder or images not in ("jpeg", "png"):
            raise SystemExit(f"{item!r} is not NAME=FOLDER[:SCENES[:jpeg|png]]")
        folder = Path(folder)
        scenes = [slim(s, images, quality, chroma)
                  for s in scenes_of(folder, int(count) if count else None)]
        if not scenes:
            raise SystemExit(f"{folder}: no scenes in its chunk files")
        # the stage folder the source had: a test root's scenes under test/, a train stage's
        # under train/ (what dataset.roots reads for training)
        test_root = (folder / "test").is_dir()
        stage = out / name / ("test" if test_root else folder.name)
        stage.mkdir(parents=True, exist_ok=True)
        write_index(stage, {s["key"]: "000000.torch" for s in scenes})
        buffer = io.BytesIO()
        torch.save(scenes, buffer)
        (stage / "000000.torch.xz").write_bytes(lzma.compress(buffer.getvalue(), preset=6))
        for index in folder.glob("evaluation_index_*.json"):  # where the source had them
            shutil.copyfile(index, (out / name if test_root else stage) / index.name)
        size = sum(f.stat().st_size for f in (out / name).rglob("*") if f.is_file())
        print(f"{name}: {len(scenes)} scenes from {folder}, {images} images, "
              f"{size / 1e6:.1f} MB in {out / name}")


def unpack(folder: Path) -> None:
    for packed in sorted(folder.rglob("*.torch.xz")):
        target = packed.with_suffix("")
        if not target.exists():
            target.write_bytes(lzma.decompress(packed.read_bytes()))
        print(f"{target}: {target.stat().st_size / 1e6:.1f} MB")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    a = sub.add_parser("pack")
    a.add_argument("sets", nargs="+", metavar="NAME=FOLDER[:SCENES[:jpeg|png]]")
    a.add_argument("--out", required=True)
    a.add_argument("--jpeg-quality", type=int, default=JPEG_QUALITY, choices=range(1, 101),
                   metavar="1..100")
    a.add_argument("--chroma", choices=tuple(SUBSAMPLING), default=CHROMA,
                   help="JPEG chroma subsampling (default: %(default)s, none)")
    b = sub.add_parser("unpack")
    b.add_argument("folder")
    args = p.parse_args(argv)
    if args.command == "pack":
        pack(args.sets, Path(args.out), args.jpeg_quality, args.chroma)
    else:
        unpack(Path(args.folder))
    return 0


if __name__ == "__main__":
    sys.exit(main())
