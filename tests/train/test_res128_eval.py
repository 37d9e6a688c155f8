"""train/studies/res128_eval.py: the 2x bicubic upsampling the 64x64 model's renders get,
against Keys' cubic convolution written here in float64 from its definition, and the whole
comparison on a small held-out set, where a model compared with itself at one size must read
zero and the upsampled renders must score as PSNR computed here says."""

import csv
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "res128_eval.py"
spec = importlib.util.spec_from_file_location("res128_eval", SCRIPT)
study = importlib.util.module_from_spec(spec)
spec.loader.exec_module(study)


def keys_cubic(t: float, a: float = -0.75) -> float:
    """Keys' cubic convolution kernel (a = -0.75, as PyTorch and OpenCV use)."""
    t = abs(t)
    if t <= 1:
        return (a + 2) * t ** 3 - (a + 3) * t ** 2 + 1
    if t < 2:
        return a * t ** 3 - 5 * a * t ** 2 + 8 * a * t - 4 * a
    return 0.0


def upsample_reference(image: np.ndarray, factor: int) -> np.ndarray:
    """[H, W] -> [factor H, factor W]: half-pixel centres (align_corners=False), the 4 taps
    clamped to the border, separable, then clamped to [0, 1]."""
    def along(rows: np.ndarray) -> np.ndarray:  # upsample the last axis
        n = rows.shape[-1]
        out = np.zeros((*rows.shape[:-1], n * factor))
        for j in range(n * factor):
            x = (j + 0.5) / factor - 0.5
            i = int(np.floor(x))
            for k in range(i - 1, i + 3):
                out[..., j] += keys_cubic(x - k) * rows[..., min(max(k, 0), n - 1)]
        return out
    return np.clip(along(along(image).T).T, 0, 1)


def test_upsampling_is_keys_cubic_convolution_clamped():
    rng = np.random.default_rng(0)
    image = rng.uniform(size=(2, 3, 5, 6))  # two targets, RGB; overshoot at the edges
    up = study.upsample(torch.tensor(image, dtype=torch.float32), 2)
    assert up.shape == (2, 3, 10, 12)
    ref = np.stack([[upsample_reference(c, 2) for c in t] for t in image])
    # float32 arithmetic on values in [0, 1]: a few units of its 6e-8 epsilon
    assert np.abs(up.numpy() - ref).max() < 1e-6
    assert up.min() >= 0 and up.max() <= 1


@pytest.mark.slow
def test_a_model_against_itself_reads_zero_at_the_small_size(tmp_path, protocol_set):
    out = tmp_path / "out"
    assert study.main(["--model128", "tiny_baseline", "--model64", "tiny_baseline", "--data",
                       str(protocol_set), "--images", "1", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scenes"] >= 1
    at64 = summary["at64"]["psnr"]
    assert at64["mean"] == 0  # the same model on the same inputs: bit for bit
    rows = list(csv.DictReader((out / "per_scene.csv").read_text().splitlines()))
    means = summary["means"]
    assert np.isclose(means["psnr_64_up"], np.mean([float(r["psnr_64_up"]) for r in rows]))
    assert (out / "comparison.png").is_file()
    # the first scene's upsampled score from the definitions: the 64x64 render, Keys' cubic
    # in float64, PSNR = -10 log10(MSE) per target, averaged over targets
    from usplat_dr.data.types import model_inputs
    from usplat_dr.evaluation import held_out_scenes, load_example
    from usplat_dr.training.loader import load
    big, index, scenes = held_out_scenes(protocol_set, "standard", 1, size=128)
    small = {**big, "image_shape": [64, 64]}
    b64, b128 = load_example(small, index, scenes[0]), load_example(big, index, scenes[0])
    with torch.no_grad():
        pred = load("tiny_baseline").eval()(*model_inputs(b64, "cpu")).color[0].clamp(0, 1)
    gt = b128["target"]["image"][0].double().numpy()
    scores = []
    for t in range(len(gt)):
        up = np.stack([upsample_reference(c, 2) for c in pred[t].double().numpy()])
        scores.append(-10 * np.log10(np.mean((up - gt[t]) ** 2)))
    # float32 renders and upsampling against float64: far below 1e-3 dB
    assert abs(float(rows[0]["psnr_64_up"]) - np.mean(scores)) < 1e-3


@pytest.mark.slow
def test_one_octave_up_names_its_columns_by_size(tmp_path, protocol_set):
    # --size 32 on the 32x32 set: the same comparison at 32 and 16 (as gpu-train runs it at
    # 256 and 128), each key named by its size
    out = tmp_path / "out"
    assert study.main(["--model-large", "tiny_baseline", "--model-small", "tiny_baseline",
                       "--size", "32", "--data", str(protocol_set), "--images", "0",
                       "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["size"] == 32 and summary["model32"] == "tiny_baseline"
    assert {"psnr_32", "psnr_16_up", "psnr_32_at16", "abs_rel_16"} <= set(summary["means"])
    assert summary["at16"]["psnr"]["mean"] == 0  # the same model at the small size
    header = (out / "per_scene.csv").read_text().splitlines()[0].split(",")
    assert "psnr_16_up" in header and not any("128" in h or "64" in h for h in header)
    with pytest.raises(SystemExit):
        study.main(["--model-large", "x", "--size", "33", "--data", "d", "--out", str(out)])


@pytest.mark.slow
def test_gaussians_rendered_at_another_size(tmp_path, protocol_set):
    # the small model's Gaussians drawn at the large size: at its own size they are its render
    # bit for bit (the same Gaussians, the same rasteriser), and --rendered-up scores them
    from usplat_dr.evaluation import held_out_scenes, load_example
    from usplat_dr.training.loader import load
    big, index, scenes = held_out_scenes(protocol_set, "standard", 1, size=32)
    model = load("tiny_baseline").eval()
    one = load_example({**big, "image_shape": [16, 16]}, index, scenes[0])
    own, _ = study.render(model, one)
    assert torch.equal(study.render_at(model, one, (16, 16)), own)
    large = study.render_at(model, one, (32, 32))
    # drawn anew at twice the size, not the render's pixels repeated (the rasteriser at any
    # size is tested against its dense reference in tests/render)
    assert large.shape[-2:] == (32, 32) and 0 <= large.min() and large.max() <= 1
    assert not torch.equal(large, own.repeat_interleave(2, -1).repeat_interleave(2, -2))
    out = tmp_path / "out"
    assert study.main(["--model-large", "tiny_baseline", "--model-small", "tiny_baseline",
                       "--size", "32", "--data", str(protocol_set), "--images", "1",
                       "--rendered-up", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert {"psnr_16_rendered_up", "ssim_16_rendered_up"} <= set(summary["means"])
    from PIL import Image
    with Image.open(out / "comparison.png") as im:  # GT | large | upsampled | drawn large
        assert im.size == (4 * 32, 32)
    assert set(summary["rendered_up"]) == {"psnr", "ssim", "against_upsampled_psnr"}
