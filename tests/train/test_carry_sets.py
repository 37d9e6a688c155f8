"""train/studies/carry_sets.py: a packed and unpacked set is the rendered set, less what
nothing reads (material maps, Mitsuba descriptions), with its images JPEG-encoded or kept, and
the data loader reads it as it reads the rendered one."""

import importlib.util
import io
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from usplat_dr.data.dataset import dataset_from_section

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "carry_sets.py"
spec = importlib.util.spec_from_file_location("carry_sets", SCRIPT)
carry = importlib.util.module_from_spec(spec)
spec.loader.exec_module(carry)


def _scenes(stage: Path) -> list[dict]:
    return [s for f in sorted(stage.glob("*.torch")) for s in torch.load(f, weights_only=False)]


def test_pack_then_unpack_gives_the_scenes_back(tmp_path, trainer_set):
    root = trainer_set
    out = tmp_path / "packed"
    carry.main(["pack", "--out", str(out), f"train={root / 'train'}:1:jpeg",
                f"heldout={root}::png"])
    assert not list(out.rglob("*.torch"))  # only the compressed files travel
    carry.main(["unpack", str(out)])

    original = _scenes(root / "train")[:1]
    packed = _scenes(out / "train" / "train")
    assert [s["key"] for s in packed] == [original[0]["key"]]
    a, b = original[0], packed[0]
    assert "materials" not in b and "mitsuba" not in b
    assert torch.equal(a["cameras"], b["cameras"]) and torch.equal(a["depths"], b["depths"])
    for x, y in zip(a["images"], b["images"]):
        assert bytes(y[:2].tolist()) == b"\xff\xd8"  # JPEG's start-of-image marker
        xs, ys = (np.asarray(Image.open(io.BytesIO(im.numpy().tobytes())).convert("RGB"),
                             dtype=np.float64) for im in (x, y))
        # JPEG at quality 95 without chroma subsampling reads 36.8-38 dB against the PNG on
        # these 32x32 renders (37-45 dB on the 64x64 sets); another frame of the scene reads
        # 18 dB and swapped colour channels 27 dB, so 32 dB tells them apart
        assert 10 * np.log10(255**2 / np.square(xs - ys).mean()) > 32
    held = _scenes(out / "heldout" / "test")
    assert len(held) == 2  # every scene when SCENES is left out
    assert held[0]["images"][0].tolist() == _scenes(root / "test")[0]["images"][0].tolist()
    assert (out / "heldout" / "evaluation_index_standard.json").is_file()
    assert (out / "train" / "train" / "index.json").is_file()

    # the data loader reads the packed training stage as a rendered one
    ds = dataset_from_section({"name": "synth", "roots": [str(out / "train")],
                               "image_shape": [32, 32]}, "train")
    example = next(iter(ds))
    assert example["context"]["image"].shape[-2:] == (32, 32)
