"""train/studies/oracle_delta.py --between-frames: the frames it fits and scores, its
interpolated and linear Delta W against dense float64 references, and at zero steps every
predictor renders (a); and its target offsets (--targets)."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.model.test_uniquesplat import scene
from tests.train.test_oracle_delta import batch_of, oracle
from usplat_dr.data.synth.render import GLOSSY, TEXTURED
from usplat_dr.evaluation.metrics import psnr
from usplat_dr.model import UniqueSplat
from usplat_dr.model.hypernet.hypernetwork import LayerDelta

transfer = oracle  # oracle_delta.py --between-frames


def test_frames_between_the_context_views_become_targets(tmp_path):
    index = {"s0": {"context": [2, 10], "target": [5, 6, 7]}, "s1": None,
             "s2": {"context": [4, 1], "target": [2]}}  # a gap of 3: too short, left out
    assert transfer.between_frames_index(index) == {
        "s0": {"context": [2, 10], "target": [3, 4, 5, 6, 7, 8, 9]}}
    path = tmp_path / "index.json"
    path.write_text(json.dumps(index))
    spread = json.loads(Path(oracle.offset_index(str(path), [1, 4, 7], tmp_path)).read_text())
    assert spread == {"s0": {"context": [2, 10], "target": [3, 6, 9]}}  # s2's gap is too short


def dense(d: LayerDelta) -> np.ndarray:
    """[T, O*I*k*k + O]: each row's Delta W in float64, from its factors."""
    full = np.einsum("tor,trikl->toikl", d.u.double().numpy(), d.v.double().numpy())
    return np.concatenate([full.reshape(len(full), -1), d.bias.double().numpy()], 1)


def random_delta(g, t: int, o=3, i=2, k=3, r=2) -> LayerDelta:
    return LayerDelta(bias=torch.randn(t, o, generator=g), u=torch.randn(t, o, r, generator=g),
                      v=torch.randn(t, r, i, k, k, generator=g))


def test_midpoints_and_linear_delta_w_match_dense_references():
    g = torch.Generator().manual_seed(0)
    d = random_delta(g, 4)
    mid = dense(transfer.midpoints({"x": d})["x"])
    ref = dense(d)
    # float32 factors, float64 products: 1e-6 relative
    np.testing.assert_allclose(mid, (ref[:-1] + ref[1:]) / 2, rtol=1e-5, atol=1e-6)
    d0, d1 = random_delta(g, 1), random_delta(g, 1)
    ts = torch.tensor([-0.5, 0.0, 0.25])
    lin = dense(transfer.linear_deltas({"x": d0}, {"x": d1}, ts)["x"])
    ref = dense(d0) + ts.double().numpy()[:, None] * dense(d1)
    np.testing.assert_allclose(lin, ref, rtol=1e-5, atol=1e-6)


def test_at_zero_steps_every_predictor_renders_a():
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="baseline").eval()
    for p in model.parameters():
        p.requires_grad_(False)
    args = scene(n=5, seed=1)  # offsets 1..5 of a gap of 6: fit 1, 3, 5; scored 2, 4
    gt = torch.rand(1, 5, 3, 64, 64, generator=torch.Generator().manual_seed(2))
    batch = batch_of(args, gt)
    batch["context"]["index"] = torch.tensor([[0, 6]])
    specs = tuple(model.conv_spec(n) for n in oracle.INJECTABLE_ALL)
    out = transfer.fit_transfer(model, batch, specs, rank=2, steps=0, lr=1e-2, seed=0)
    with torch.no_grad():
        plain = psnr(model(*args).color[0], gt[0]).tolist()
    # Delta W = 0 in every predictor (U = 0): (a)'s renders up to the rank-r path's rounding
    for key in ("a", "shared", "interpolated", "linear"):
        assert out[key] == pytest.approx([plain[1], plain[3]], abs=1e-3), key
    for key in ("in_sample_shared", "in_sample_per_target"):
        assert out[key] == pytest.approx(plain[0::2], abs=1e-3), key


def test_shiny_pixels_are_scored_alone_and_a_frame_without_any_is_nan():
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="baseline").eval()
    for p in model.parameters():
        p.requires_grad_(False)
    args = scene(n=5, seed=1)
    gt = torch.rand(1, 5, 3, 64, 64, generator=torch.Generator().manual_seed(2))
    batch = batch_of(args, gt)
    batch["context"]["index"] = torch.tensor([[0, 6]])
    material = torch.full((1, 5, 64, 64), float(TEXTURED))
    material[0, 1, 10:30, 20:50] = GLOSSY  # scored frame at offset 2: a shiny patch
    batch["target"]["material"] = material  # offset 4 (index 3): no shiny pixel
    specs = tuple(model.conv_spec(n) for n in oracle.INJECTABLE_ALL)
    out = transfer.fit_transfer(model, batch, specs, rank=2, steps=0, lr=1e-2, seed=0,
                                pixels="shiny")
    with torch.no_grad():
        pred = model(*args).color[0, 1].clamp(0, 1)
    # the PSNR of the patch alone, written from its definition in float64
    mse = (pred[:, 10:30, 20:50].double() - gt[0, 1, :, 10:30, 20:50].double()).square().mean()
    expected = -10 * math.log10(mse.item())
    for key in ("a", "shared", "interpolated", "linear"):
        # (a)'s renders up to the rank-r path's rounding (as above)
        assert out[key][0] == pytest.approx(expected, abs=1e-3), key
        assert math.isnan(out[key][1]), key
