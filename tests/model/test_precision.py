"""bfloat16 inference (``UniqueSplat.inference_precision``): the geometry stays float32, the
renders stay close to float32's, training ignores it, and a bad value is an error."""

import logging
import os
from pathlib import Path

import pytest
import torch

from tests.model.conftest import two_view_cameras
from tests.model.test_uniquesplat import scene
from usplat_dr.model.encoder.cost_volume import plane_sweep_correlation
from usplat_dr.training.checkpoints import load_model

CHECKPOINT = Path(__file__).parents[2] / "checkpoints" / "tiny_baseline.pt"


@pytest.fixture(autouse=True)
def _quiet_resnet(caplog):
    caplog.set_level(logging.ERROR, logger="usplat_dr.model.hypernet.resnet")


def test_plane_sweep_under_bfloat16_autocast_keeps_float32_geometry():
    # At 64x64 features the gathered corner index y * 64 + x reaches 4095, which bfloat16
    # (8-bit mantissa) cannot hold: before the sampling grid was pinned to float32 this
    # raised "index 4096 is out of bounds". Now only the correlation's matrix product runs in
    # bfloat16.
    g = torch.Generator().manual_seed(0)
    features = torch.randn(1, 2, 32, 64, 64, generator=g)
    e, k = two_view_cameras(1, 2)
    disparities = torch.linspace(0.01, 1.0, 8).repeat(2, 1)
    ref = plane_sweep_correlation(features, e, k, disparities)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = plane_sweep_correlation(features, e, k, disparities)
    # bfloat16 rounds each operand to 2^-9 relative; dot products over 32 channels of
    # random features then differ by up to ~1% of the largest value (0.84% measured). The
    # lower bound shows the product did run in bfloat16.
    rel = (out.float() - ref).abs().max() / ref.abs().max()
    assert 1e-4 < rel < 0.03


@pytest.fixture(scope="module")
def model():
    return load_model(CHECKPOINT)[0]


@pytest.mark.parametrize("seed", [0, 1])
def test_bfloat16_inference_renders_close_to_float32(model, seed):
    args = scene(64, seed=seed)
    model.eval()
    with torch.no_grad():
        model.inference_precision = "float32"
        ref = model(*args)
        model.inference_precision = "bfloat16"
        try:
            out = model(*args)
        finally:
            model.inference_precision = "float32"
    for name in ("means", "covariances", "harmonics", "opacities"):
        assert getattr(out.gaussians, name).dtype == torch.float32, name
    assert out.color.dtype == torch.float32
    assert out.aux["context_depths"].dtype == torch.float32
    mse = ((out.color - ref.color) ** 2).mean()
    # The shipped tiny network on noise images: the two renders agree to 35.6-42.1 dB PSNR
    # (measured on seeds 0-2); a bfloat16 path that broke the geometry or the colours would
    # fall below 20, and one that never ran in bfloat16 would be identical (infinite).
    # On the held-out synthetic set the protocol's PSNR moved by +0.013 dB.
    assert 30 < -10 * torch.log10(mse) < 80


def test_precision_can_change_between_calls_of_a_full_model():
    # (c) caches W between inference calls; a W computed under bfloat16 autocast must not be
    # reused by a later float32 call (a dtype mismatch in the convolution, or silently
    # different numbers).
    full = load_model(CHECKPOINT.with_name("tiny_full.pt"))[0].eval()
    args = scene(64, seed=0)
    with torch.no_grad():
        ref = full(*args, render=False).gaussians.means
        full.inference_precision = "bfloat16"
        full(*args, render=False)
        full.inference_precision = "float32"
        again = full(*args, render=False).gaussians.means
    assert torch.equal(again, ref)


def test_training_ignores_inference_precision(model):
    args = scene(64, seed=0)
    model.train()
    try:
        with torch.no_grad():
            ref = model(*args, render=False)
            model.inference_precision = "bfloat16"
            out = model(*args, render=False)
    finally:
        model.inference_precision = "float32"
        model.eval()
    # No autocast while training: the same float32 operations, bit for bit.
    assert torch.equal(out.gaussians.means, ref.gaussians.means)


def test_bad_inference_precision_names_the_setting(model):
    model.inference_precision = "float16"
    try:
        with pytest.raises(ValueError, match="inference_precision must be 'float32' or "
                                             "'bfloat16', got 'float16'"):
            model(*scene(64), render=False)
    finally:
        model.inference_precision = "float32"


def test_bfloat16_with_onednn_capped_at_avx2_warns(monkeypatch, caplog):
    # oneDNN capped at AVX2 has no bfloat16 instructions: usplat eval says so rather than
    # running 14x slower in silence (usplat leaves the cap off for bfloat16; a user may set it)
    from usplat_dr.jobs.eval import warn_slow_bfloat16

    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    with caplog.at_level(logging.WARNING, logger="usplat_dr.jobs.eval"):
        warn_slow_bfloat16()
    assert "Unset it for the fast path" in caplog.text


def test_usplat_leaves_torch_unpinned_for_bfloat16_only(monkeypatch):
    # torch's pins are read when torch loads, so the decision is made from the command line
    # before it: a fresh interpreter per case, with none of the pins in its environment.
    import subprocess
    import sys

    from usplat_dr import portable

    env = {k: v for k, v in os.environ.items() if k not in portable.TORCH_ENV
           and k != portable.ENV_VAR}
    code = ("import os, sys; from usplat_dr import cli; from usplat_dr import portable; "
            "portable.enable(torch_pins=not cli.asks_bfloat16(sys.argv[1:])); "
            "print(os.environ.get('ONEDNN_MAX_CPU_ISA'), os.environ.get('USPLAT_PORTABLE'))")
    for argv, expected in ((["eval", "--precision", "bfloat16"], "None 1"),
                           (["eval", "--precision=float32"], "AVX2 1"), (["eval"], "AVX2 1")):
        out = subprocess.run([sys.executable, "-c", code, *argv], env=env, check=True,
                             capture_output=True, text=True).stdout.split("\n")[-2]
        assert out == expected, argv
