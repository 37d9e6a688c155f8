"""The view-specificity meter: it reads exactly 0 at the zero-initialised start, sees a Delta W
set by hand to differ between targets (spread and PSNR against float64 references written from
the definitions), and its full form renders what the rank-r form renders."""

import logging
import math

import numpy as np
import pytest
import torch

from tests.model.test_uniquesplat import scene
from usplat_dr.evaluation.verdict import t_interval
from usplat_dr.evaluation.view_specificity import (
    LIVE_BOUND_DB,
    full_delta,
    layer_spread,
    manipulation_check,
    read_batch,
    scene_mean,
    summarise,
)
from usplat_dr.model import UniqueSplat
from usplat_dr.model.hypernet.hypernetwork import LayerDelta
from usplat_dr.model.uniquesplat import StudyHooks


@pytest.fixture(autouse=True)
def _quiet_resnet(caplog):
    caplog.set_level(logging.ERROR, logger="usplat_dr.model.hypernet.resnet")


def batch_of(args, n_targets: int, seed: int = 1) -> dict:
    """A collated batch around ``scene()``'s cameras, with random target images."""
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(1, n_targets, 3, 64, 64, generator=g)
    return {"context": {"image": args.images, "extrinsics": args.extrinsics,
                        "intrinsics": args.intrinsics, "near": args.near, "far": args.far},
            "target": {"image": gt, "extrinsics": args.target_extrinsics,
                       "intrinsics": args.target_intrinsics, "near": args.target_near,
                       "far": args.target_far},
            "scene": ["s0"]}


def psnr64(pred: torch.Tensor, gt: torch.Tensor) -> np.ndarray:
    """PSNR per image in float64, from its definition (both clipped to [0, 1])."""
    p, g = pred.double().clamp(0, 1).numpy(), gt.double().clamp(0, 1).numpy()
    return -10 * np.log10(((p - g) ** 2).mean((-3, -2, -1)))


def test_the_zero_initialised_start_reads_exactly_zero():
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="full")  # Delta W = 0 exactly
    args = scene(n=3)
    assert model.training
    (r,) = read_batch(model, batch_of(args, 3))
    assert model.training  # the meter computes in evaluation mode and gives the mode back
    # Delta W is exactly 0 for every target: the three renders are the same arithmetic
    assert all(v == 0 for v in r.spread.values()) and all(v == 0 for v in r.size.values())
    assert r.d_mean == r.d_mean_abs == r.d_zero == r.d_zero_abs == 0
    s = summarise([r, r])
    assert not s.live and s.psnr["d_mean_abs"][0] == 0


def hand_set(model, args, scale: float):
    """A Delta W set by hand on every layer: +D for target 0, -D for target 1 (their mean is
    0), D random with ||D|| = ``scale`` ||W||."""
    g = torch.Generator().manual_seed(3)
    weights = model.generated_weights()
    deltas = {}
    for name, (w, bias) in weights.items():
        d_w = torch.randn(w.shape, generator=g)
        d_b = torch.randn(bias.shape, generator=g)
        norm = torch.cat((d_w.flatten(), d_b)).norm()
        norm_w = torch.cat((w.flatten(), bias)).norm()
        d_w, d_b = d_w * scale * norm_w / norm, d_b * scale * norm_w / norm
        deltas[name] = LayerDelta(bias=torch.stack((d_b, -d_b)),
                                  full=torch.stack((d_w, -d_w)).detach())
    model.view_delta_w = lambda *a, **k: deltas
    return deltas


def test_a_delta_w_that_differs_between_targets_is_seen():
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="full").eval()
    args = scene(n=2)
    batch = batch_of(args, 2)
    scale = 0.5
    deltas = hand_set(model, args, scale)
    (r,) = read_batch(model, batch)
    # Spread: targets +D and -D around a mean of 0, so sqrt(mean ||D_n - 0||^2) / ||W|| = scale
    # and the mean's size 0 (float64 sums of float32 values: 1e-6 relative)
    for name in deltas:
        assert r.spread[name] == pytest.approx(scale, rel=1e-5), name
        assert r.size[name] < 1e-7, name
    # The scene-mean Delta W is 0 here, so the mean arm and the zero arm are one render
    assert r.d_mean == r.d_zero and r.d_mean_abs == r.d_zero_abs
    # PSNR from its definition in float64 on renders made without the meter's code:
    # forward with the hand-set Delta W against forward with none (the (b)-like renders)
    with torch.no_grad():
        own = model(*args, hooks=StudyHooks(delta_w=deltas)).color[0]
        zeros = {k: LayerDelta(bias=0 * d.bias, full=0 * d.full) for k, d in deltas.items()}
        zero = model(*args, hooks=StudyHooks(delta_w=zeros)).color[0]
    d = psnr64(own, batch["target"]["image"][0]) - psnr64(zero, batch["target"]["image"][0])
    # float32 PSNR of float32 renders of 64x64 images: 1e-4 dB
    assert r.d_mean == pytest.approx(d.mean(), abs=1e-4)
    assert r.d_mean_abs == pytest.approx(np.abs(d).mean(), abs=1e-4)
    # and it is large enough to see: half of ||W|| moves each target by more than the bound
    assert r.d_mean_abs > LIVE_BOUND_DB


def test_identical_delta_w_for_every_target_reads_zero_spread_and_no_psnr_difference():
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="full").eval()
    args = scene(n=2)
    deltas = hand_set(model, args, 0.05)
    same = {k: LayerDelta(bias=d.bias[:1].expand(2, -1).clone(),
                          full=d.full[:1].expand(2, *d.full.shape[1:]).clone())
            for k, d in deltas.items()}
    model.view_delta_w = lambda *a, **k: same
    (r,) = read_batch(model, batch_of(args, 2))
    # (D + D) / 2 == D exactly in float arithmetic: the mean arm is the own arm, bit for bit
    assert all(v == 0 for v in r.spread.values())
    assert r.d_mean == 0 and r.d_mean_abs == 0
    assert r.d_zero_abs > 0  # the constant Delta W still changes the renders against 0
    for name in same:
        assert r.size[name] == pytest.approx(0.05, rel=1e-5)


def test_layer_spread_matches_a_float64_reference():
    g = torch.Generator().manual_seed(0)
    b, n, o, i, k, r = 2, 3, 5, 4, 3, 2
    d = LayerDelta(bias=torch.randn(b * n, o, generator=g),
                   u=torch.randn(b * n, o, r, generator=g),
                   v=torch.randn(b * n, r, i, k, k, generator=g))
    w = (torch.randn(o, i, k, k, generator=g), torch.randn(o, generator=g))
    spread, size = layer_spread(d, w, b, n)
    u, v = d.u.double().numpy(), d.v.double().numpy()
    flat = np.concatenate([np.einsum("tor,trikl->toikl", u, v).reshape(b * n, -1),
                           d.bias.double().numpy()], 1).reshape(b, n, -1)
    norm_w = math.sqrt((w[0].double() ** 2).sum() + (w[1].double() ** 2).sum())
    mean = flat.mean(1, keepdims=True)
    ref_spread = np.sqrt(((flat - mean) ** 2).sum(-1).mean(1)) / norm_w
    ref_size = np.linalg.norm(mean[:, 0], axis=-1) / norm_w
    # float32 products of the factors: 1e-6 relative
    np.testing.assert_allclose(spread.numpy(), ref_spread, rtol=1e-5)
    np.testing.assert_allclose(size.numpy(), ref_size, rtol=1e-5)
    m = scene_mean(d, b, n)
    np.testing.assert_allclose(m.full.view(b, n, -1)[:, 1].double().numpy(),
                               np.einsum("tor,trikl->toikl", u, v).reshape(b, n, -1).mean(1),
                               rtol=1e-4, atol=1e-5)


def test_the_full_form_renders_what_the_rank_r_form_renders():
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="full", delta_init_std=0.5).eval()
    args = scene(n=3)
    with torch.no_grad():
        deltas = model.view_delta_w(args.images, args.extrinsics, args.intrinsics,
                                    args.target_extrinsics, args.target_intrinsics,
                                    args.target_near, args.target_far)
        low = model(*args, hooks=StudyHooks(delta_w=deltas)).color
        fulls = {k: full_delta(d) for k, d in deltas.items()}
        full = model(*args, hooks=StudyHooks(delta_w=fulls)).color
    # A full convolution against base + U (V x): float32 reassociation in the heads (1e-6 on
    # the Gaussians), which rendering amplifies where a Gaussian's edge crosses a pixel
    # (measured: 14 of 36,864 values beyond 2e-5, the largest 1.3e-4); what the meter reads
    # from it, PSNR, moves by < 1e-4 dB.
    torch.testing.assert_close(full, low, rtol=0, atol=1e-3)
    assert (full - low).abs().mean() < 1e-6
    gt = torch.rand_like(low)
    assert (psnr64(full[0], gt[0]) - psnr64(low[0], gt[0])).max() < 1e-4
    assert max(d.u.abs().max() for d in deltas.values()) > 0  # Delta W is not 0 here


def test_bad_inputs_name_the_argument():
    model = UniqueSplat.from_preset("tiny", variant="agnostic")
    args = scene(n=2)
    with pytest.raises(ValueError, match="view-specific branch"):
        read_batch(model, batch_of(args, 2))
    full = UniqueSplat.from_preset("tiny", variant="full")
    one = scene(n=1)
    with pytest.raises(ValueError, match=">= 2 target views"):
        read_batch(full, batch_of(one, 1))
    with pytest.raises(ValueError, match="readings is empty"):
        summarise([])


def test_t_interval_is_students():
    lo, hi = t_interval([1.0, 2.0, 3.0])
    # mean 2, sd 1, t(0.975, 2) = 4.3027: 2 -+ 4.3027 / sqrt(3)
    assert lo == pytest.approx(2 - 4.302653 / math.sqrt(3), rel=1e-6)
    assert hi == pytest.approx(2 + 4.302653 / math.sqrt(3), rel=1e-6)
    assert all(math.isnan(x) for x in t_interval([1.0]))


def test_manipulation_check_reads_an_evaluations_per_scene_csv(tmp_path):
    path = tmp_path / "per_scene.csv"
    path.write_text("split,scene,psnr,view_spread,view_psnr_abs\n"
                    "standard,s0,20,1e-3,0.04\nstandard,s1,21,3e-3,0.08\n"
                    "wide,s0,19,9e-1,9.0\n")  # another split: not read
    c = manipulation_check(path)
    assert c["scenes"] == 2 and c["spread_rel_w"] == 3e-3
    assert c["psnr_abs_db"] == pytest.approx(0.06) and c["live"]  # 0.06 >= 0.05
    lo, hi = t_interval([0.04, 0.08])
    assert (c["low"], c["high"]) == (lo, hi)
    (tmp_path / "a.csv").write_text("split,scene,psnr\nstandard,s0,20\n")  # no meter: (a)
    assert manipulation_check(tmp_path / "a.csv") is None
