"""The Gaussian budget chosen at inference (model/budget.py): top-K against numpy's argsort,
K as a count and a fraction, the unbudgeted output bit for bit, the relaxed mask against the
hard one, gradients into the importance head, the adaptation's start and its rule, and the
errors that name the argument."""

import logging
import math

import numpy as np
import pytest
import torch

from tests.model.test_uniquesplat import scene
from usplat_dr.model import UniqueSplat
from usplat_dr.model.budget import (
    GaussianBudget,
    ImportanceHead,
    adapt,
    apply_budget,
    budget_count,
    coverage_rule,
    dither_offsets,
    local_fraction,
    ranks,
    soft_mask,
    top_k,
)
from usplat_dr.model.types import Gaussians

FIELDS = ("means", "covariances", "harmonics", "opacities", "scales", "rotations")


@pytest.fixture(autouse=True)
def _quiet_resnet(caplog):
    caplog.set_level(logging.ERROR, logger="usplat_dr.model.hypernet.resnet")


def random_gaussians(s: int, g: int, seed: int = 0) -> Gaussians:
    gen = torch.Generator().manual_seed(seed)
    a = torch.randn(s, g, 3, 3, generator=gen)
    return Gaussians(means=torch.randn(s, g, 3, generator=gen),
                     covariances=a @ a.transpose(-1, -2) + 0.1 * torch.eye(3),
                     harmonics=torch.randn(s, g, 3, 4, generator=gen),
                     opacities=torch.rand(s, g, generator=gen),
                     scales=torch.rand(s, g, 3, generator=gen) + 0.1,
                     rotations=torch.randn(s, g, 4, generator=gen))


@pytest.mark.parametrize("k", [1, 7, 30, 63, 64])
def test_top_k_is_numpys_stable_argsort_with_ties(k):
    # Integer scores in 0..4 over 64 Gaussians: ties everywhere, and at the K-th place.
    gen = torch.Generator().manual_seed(k)
    scores = torch.randint(0, 5, (3, 64), generator=gen).float()
    index, rank = top_k(scores, k)
    for row in range(3):
        ref = np.argsort(-scores[row].numpy(), kind="stable")[:k]  # ties: lower index first
        assert index[row].tolist() == sorted(ref.tolist())
        # each kept Gaussian's rank is its place in numpy's order
        assert rank[row].tolist() == [ref.tolist().index(i) for i in index[row].tolist()]
        full = np.argsort(-scores[row].numpy(), kind="stable")
        assert ranks(scores)[row].tolist() == np.argsort(full, kind="stable").tolist()


def test_budget_count_takes_a_count_or_a_fraction():
    assert budget_count(1, 100) == 1 and budget_count(100, 100) == 100
    assert budget_count(10**9, 100) == 100  # more than the model has: all of them
    assert budget_count(np.int64(5), 100) == 5
    assert budget_count(0.3, 100) == 30 and budget_count(0.304, 1000) == 304
    assert budget_count(1.0, 100) == 100 and budget_count(1e-6, 100) == 1  # at least one
    for bad in (0, -3, 0.0, 1.5, -0.1, math.nan, True, "0.3", None):
        with pytest.raises(ValueError, match="budget"):
            budget_count(bad, 100)


def test_hard_budget_keeps_k_in_the_gaussians_order():
    g = random_gaussians(2, 50)
    for budget, k in ((12, 12), (0.3, 15)):
        out = apply_budget(g, budget, "opacity")
        assert out.kept == k
        for row in range(2):
            ref = sorted(np.argsort(-g.opacities[row].numpy(), kind="stable")[:k].tolist())
            assert torch.nonzero(out.kept_mask[row])[:, 0].tolist() == ref
            for name in FIELDS:  # the same Gaussians, untouched (no adaptation for controls)
                assert torch.equal(getattr(out.gaussians, name)[row],
                                   getattr(g, name)[row, ref])
    # random: seeded, K of them, a different draw for another seed
    a, b = apply_budget(g, 10, "random", seed=1), apply_budget(g, 10, "random", seed=1)
    c = apply_budget(g, 10, "random", seed=2)
    assert torch.equal(a.kept_mask, b.kept_mask) and not torch.equal(a.kept_mask, c.kept_mask)
    assert (a.kept_mask.sum(1) == 10).all()
    with pytest.raises(ValueError, match="rank_by"):
        apply_budget(g, 10, "size")
    with pytest.raises(ValueError, match="budget_tau"):
        apply_budget(g, 10, "opacity", tau=0.0)


#: The classic 8x8 Bayer index matrix (ordered dithering), as printed in the literature.
BAYER8 = np.array([[0, 32, 8, 40, 2, 34, 10, 42], [48, 16, 56, 24, 50, 18, 58, 26],
                   [12, 44, 4, 36, 14, 46, 6, 38], [60, 28, 52, 20, 62, 30, 54, 22],
                   [3, 35, 11, 43, 1, 33, 9, 41], [51, 19, 59, 27, 49, 17, 57, 25],
                   [15, 47, 7, 39, 13, 45, 5, 37], [63, 31, 55, 23, 61, 29, 53, 21]])


def test_dither_offsets_are_the_bayer_thresholds():
    d = dither_offsets(2, 12, 20).view(2, 12, 20).double()
    ys, xs = np.meshgrid(np.arange(12) % 8, np.arange(20) % 8, indexing="ij")
    ref = -np.log((BAYER8[ys, xs] + 0.5) / 64)
    for v in range(2):  # the same tile in every view; float32 of a float64 log: 1e-6
        np.testing.assert_allclose(d[v].numpy(), ref, rtol=1e-6)
    # two Gaussians per pixel: consecutive levels of 128
    d2 = dither_offsets(1, 8, 8, 2).view(8, 8, 2).double().numpy()
    np.testing.assert_allclose(d2[..., 1], -np.log((2 * BAYER8 + 1.5) / 128), rtol=1e-6)


def box_fraction(kept: np.ndarray, window: int = 9) -> np.ndarray:
    """Reference of ``local_fraction`` for one view [H, W]: the mean of ``kept`` over the
    window around each pixel, clipped at the border, by explicit loops."""
    h, w = kept.shape
    r = window // 2
    out = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            out[y, x] = kept[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1].mean()
    return out


def test_local_fraction_counts_the_kept_neighbours():
    gen = torch.Generator().manual_seed(5)
    kept = torch.rand(2, 2 * 10 * 13, generator=gen) < 0.3  # 2 sets, 2 views of 10x13
    f = local_fraction(kept, (2, 10, 13, 1)).view(2, 2, 10, 13)
    for s in range(2):
        for v in range(2):  # float32 averages of <= 81 ones and zeros: 1e-6
            np.testing.assert_allclose(
                f[s, v].numpy(), box_fraction(kept.view(2, 2, 10, 13)[s, v].numpy().astype(
                    float)), atol=1e-6)


def test_soft_mask_tends_to_the_hard_mask():
    # Distinct scores at least 1e-3 apart (a permutation, scaled): the kept K are exactly 1,
    # the dropped ones sigmoid(-gap / 2 tau) < 1/2; at tau = 1e-5 within exp(-50) of 0.
    gen = torch.Generator().manual_seed(0)
    scores = torch.stack([torch.randperm(200, generator=gen) for _ in range(3)]).double()
    scores = scores * 1e-3
    for k in (1, 50, 199):
        index, _ = top_k(scores, k)
        hard = torch.zeros_like(scores).scatter_(1, index, 1.0)
        errors = [(soft_mask(scores, k, tau) - hard).abs().max().item()
                  for tau in (1e-2, 1e-3, 1e-5)]
        assert errors[0] > errors[1] > errors[2] and errors[2] < 1e-12, errors
    assert torch.equal(soft_mask(scores, 200, 0.1), torch.ones_like(scores))  # keeps all


def test_soft_mask_gradient_keeps_the_budget():
    # d mask_i / d s_j = sigma'_i / tau (delta_ij - w_j), w = sigma' / sum sigma' (the
    # threshold of a budget of K moving with the scores), written out in float64; the
    # mask's sum then has zero gradient.
    gen = torch.Generator().manual_seed(6)
    scores = torch.randn(1, 12, generator=gen, dtype=torch.float64)
    k, tau = 4, 0.7
    jac = torch.autograd.functional.jacobian(lambda x: soft_mask(x, k, tau), scores)[0, :, 0]
    top = scores.sort(descending=True).values[0]
    t = 0.5 * (top[k - 1] + top[k])
    sig = torch.sigmoid((scores[0] - t) / tau)
    slope = sig * (1 - sig)
    ref = slope[:, None] / tau * (torch.eye(12, dtype=torch.float64)
                                  - (slope / slope.sum())[None, :])
    torch.testing.assert_close(jac, ref, rtol=1e-12, atol=1e-12)
    assert jac.sum(0).abs().max() < 1e-12


def test_the_adaptation_starts_at_the_coverage_rule():
    head = ImportanceHead(8, 16, 1)
    gen = torch.Generator().manual_seed(7)
    log_local = -3 * torch.rand(2, 30, generator=gen)
    features = torch.randn(2, 30, 4, generator=gen)
    a, s = head.adaptation(math.log(0.2), log_local, features)
    a_ref, s_ref = coverage_rule(log_local)
    assert torch.equal(a, a_ref) and torch.equal(s, s_ref)  # the MLP's last layer is zero
    # 1/f copies and an area 1/f times larger, within the bounds (e^3 copies, e^2 scale)
    torch.testing.assert_close(a_ref, (-log_local).clamp(max=3.0), rtol=0, atol=0)
    torch.testing.assert_close(s_ref, (-0.5 * log_local).clamp(max=2.0), rtol=0, atol=0)
    assert torch.equal(coverage_rule(torch.zeros(1, 3))[0], torch.zeros(1, 3))  # f = 1


def test_adaptation_rule_and_its_identity_start():
    g = random_gaussians(2, 40, seed=3)
    g.opacities[0, :3] = torch.tensor([0.0, 1.0, 1 - 1e-7])  # the ends of the range
    zero = torch.zeros(2, 40)
    same = adapt(g, zero, zero)
    for name in FIELDS:  # a = s = 0: the same numbers, bit for bit
        assert torch.equal(getattr(same, name), getattr(g, name)), name
    # against the rule's definition in float64: opacity 1 - (1 - o)^(e^a) (the coverage of
    # e^a copies), scales e^s, covariances e^2s; float32 rounding of log1p/expm1 -> 1e-6
    gen = torch.Generator().manual_seed(4)
    a, s = torch.randn(2, 40, generator=gen), torch.randn(2, 40, generator=gen)
    out = adapt(g, a, s)
    o = g.opacities.double().clamp(max=1 - 1e-6)
    ref = 1 - (1 - o) ** a.double().exp()
    ref = torch.where(g.opacities.double() >= 1 - 1e-6, g.opacities.double(), ref)
    torch.testing.assert_close(out.opacities.double(), ref, rtol=0, atol=2e-6)
    torch.testing.assert_close(out.scales, g.scales * s.exp()[..., None])
    torch.testing.assert_close(out.covariances, g.covariances * (2 * s).exp()[..., None, None])


@pytest.mark.parametrize("variant", ["baseline", "full"])
def test_no_budget_or_all_of_them_leaves_the_output_bit_for_bit(variant):
    torch.manual_seed(0)
    plain = UniqueSplat.from_preset("tiny", variant=variant).eval()
    headed = UniqueSplat.from_preset("tiny", variant=variant, importance=True).eval()
    missing = headed.load_state_dict(plain.state_dict(), strict=False).missing_keys
    assert missing and all(k.startswith("importance.") for k in missing)
    args = scene(size=32, n=2)
    with torch.no_grad():
        ref = plain(*args)
        total = len(ref.gaussians)
        outs = [plain(*args, budget=GaussianBudget(1.0)), headed(*args),
                headed(*args, budget=GaussianBudget(total, rank_by="random"))]
    for out in outs:
        for key in ("color", "alpha", "depth"):
            assert torch.equal(getattr(out, key), getattr(ref, key)), key
        for name in FIELDS:
            assert torch.equal(getattr(out.gaussians, name), getattr(ref.gaussians, name))
        assert (out.aux["kept"] == total).all() and "importance" not in out.aux


def test_the_footprint_ranking_keeps_what_covers_most_of_each_target():
    torch.manual_seed(2)
    model = UniqueSplat.from_preset("tiny", variant="full").eval()
    args = scene(size=32, n=3)
    targets = args.targets
    with torch.no_grad():
        full = model(*args, render=False)
        out = model(*args, render=False, budget=GaussianBudget(0.2, rank_by="footprint"))
    g = full.gaussians
    k = round(0.2 * len(g))
    assert (out.aux["kept"] == k).all()
    # the scores: float64 from the equations (render/prune.py's projection is tested against
    # the reference renderer's; here the model must hand it each target's own camera)
    for t in range(3):
        w2c = torch.linalg.inv(targets.extrinsics[0, t].double())
        p = g.means[t].double() @ w2c[:3, :3].T + w2c[:3, 3]
        fx, fy = targets.intrinsics[0, t, 0, 0] * 32, targets.intrinsics[0, t, 1, 1] * 32
        zeros = torch.zeros_like(p[:, 2])
        jac = torch.stack([torch.stack([fx / p[:, 2], zeros, -fx * p[:, 0] / p[:, 2] ** 2], -1),
                           torch.stack([zeros, fy / p[:, 2], -fy * p[:, 1] / p[:, 2] ** 2], -1)],
                          -2)
        cov2 = jac @ w2c[:3, :3] @ g.covariances[t].double() @ w2c[:3, :3].T @ jac.transpose(-1, -2)
        cov2 = cov2 + 0.3 * torch.eye(2, dtype=torch.float64)  # the rasteriser's dilation
        area = (9 * math.pi * torch.linalg.det(cov2).sqrt()).clamp(max=32 * 32)
        ref = g.opacities[t].double() * area
        got = out.aux["importance"][t].double()
        shown = got >= 0  # the others are culled (-1); most Gaussians of the scene are seen
        assert shown.float().mean() > 0.5
        # float32 against float64 projection (and the frustum guard's clamp, inactive for
        # Gaussians inside the image): 1e-3 relative; a missing factor is off by >= 2x
        inside = shown & (p[:, 0].abs() < 0.4 * p[:, 2]) & (p[:, 1].abs() < 0.4 * p[:, 2])
        torch.testing.assert_close(got[inside], ref[inside], rtol=1e-3, atol=0)
        top = np.sort(np.argsort(-got.numpy(), kind="stable")[:k])
        assert torch.equal(out.gaussians.means[t], g.means[t, top])


def test_a_budget_keeps_k_per_target_ranked_as_asked(caplog):
    torch.manual_seed(1)
    plain = UniqueSplat.from_preset("tiny", variant="full").eval()
    headed = UniqueSplat.from_preset("tiny", variant="full", importance=True).eval()
    headed.load_state_dict(plain.state_dict(), strict=False)
    args = scene(size=32, n=3)
    with torch.no_grad(), caplog.at_level(logging.WARNING, logger="usplat_dr.model.uniquesplat"):
        full = plain(*args, render=False)
        control = plain(*args, budget=GaussianBudget(0.3, rank_by="opacity"))
        dither = plain(*args, budget=GaussianBudget(0.3))  # no head: dither, with a warning
        plain(*args, budget=GaussianBudget(0.3))  # warned once per model
        learned = headed(*args, budget=GaussianBudget(0.3))
    warnings = [r.message for r in caplog.records if "no importance head" in r.message]
    assert len(warnings) == 1 and "synthetic_tiny_budget.yaml" in warnings[0]
    g, k = len(full.gaussians), round(0.3 * len(full.gaussians))
    assert (control.aux["kept"] == k).all() and (control.aux["rendered"] == k).all()
    assert control.target(0, 2).means.shape == (1, k, 3)
    # per target ((c) has a set per target): the K most opaque of that target's own set
    for t in range(3):
        ref = np.argsort(-full.gaussians.opacities[t].numpy(), kind="stable")[:k]
        assert torch.equal(control.gaussians.means[t], full.gaussians.means[t, sorted(ref)])
    assert control.aux["kept_mask"].shape == (3, g)
    # dither: scores log o - log T (T the Bayer threshold of the Gaussian's pixel); the top K
    # of them, rescaled by the coverage rule from the kept fraction around each
    ys, xs = np.meshgrid(np.arange(32) % 8, np.arange(32) % 8, indexing="ij")
    offsets = np.tile(-np.log((BAYER8[ys, xs] + 0.5) / 64).reshape(-1), 2)
    o = full.gaussians.opacities.double().numpy()
    scores = dither.aux["importance"].double().numpy()
    np.testing.assert_allclose(scores, np.log(np.clip(o, 1e-6, None)) + offsets, rtol=1e-5,
                               atol=1e-5)  # float32 logs of values down to 1e-6
    for t in range(3):
        kept = np.sort(np.argsort(-dither.aux["importance"][t].numpy(), kind="stable")[:k])
        assert torch.nonzero(dither.aux["kept_mask"][t])[:, 0].tolist() == kept.tolist()
        mask = np.zeros(g)
        mask[kept] = 1
        f = np.concatenate([box_fraction(m.reshape(32, 32)).reshape(-1)
                            for m in mask.reshape(2, -1)])[kept]
        scale = np.exp(np.minimum(-0.5 * np.log(f), 2.0))
        np.testing.assert_allclose(dither.gaussians.scales[t].double().numpy(),
                                   full.gaussians.scales[t, kept].double().numpy()
                                   * scale[:, None], rtol=1e-5)  # float32 exp and log
        copies = np.minimum(1 / f, np.exp(3.0))
        ref_o = 1 - (1 - np.clip(o[t, kept], None, 1 - 1e-6)) ** copies
        np.testing.assert_allclose(dither.gaussians.opacities[t].double().numpy(), ref_o,
                                   rtol=0, atol=1e-5)  # float32 log1p/expm1
    # the untrained head (zero last layers) is dither, bit for bit
    for name in FIELDS:
        assert torch.equal(getattr(learned.gaussians, name), getattr(dither.gaussians, name))
    assert torch.equal(learned.color, dither.color)


def test_gradients_reach_the_importance_head():
    torch.manual_seed(2)
    model = UniqueSplat.from_preset("tiny", variant="baseline", importance=True).train()
    args = scene(size=32, n=2)
    out = model(*args, budget=GaussianBudget(0.25, tau=0.5))
    assert len(out.gaussians) == 2 * 32 * 32 and "budget_mask" in out.aux
    assert "unbudgeted" in out.aux  # for loss.full_render
    out.color.square().mean().backward()
    grads = {n: p.grad for n, p in model.importance.named_parameters()}
    # zero-initialised last layers: their own gradients are non-zero at once (the hidden
    # activations are not zero); the layers before them get theirs one step later
    for name in ("conv.2.weight", "adapt_mlp.2.weight", "adapt_mlp.2.bias"):
        assert grads[name] is not None and grads[name].abs().sum() > 0, name
        assert torch.isfinite(grads[name]).all(), name
    # The score's bias shifts every score alike, and the relaxed top-K's threshold moves with
    # the scores (a budget of K is kept): its gradient is 0 but for float32 rounding (~1e-10,
    # whose sign and size follow the thread count), against ~0.1 for the weights.
    assert grads["conv.2.bias"].abs().sum() < 1e-6 * grads["conv.2.weight"].abs().sum()


def test_budget_arguments_are_checked_before_the_networks_run():
    model = UniqueSplat.from_preset("tiny", variant="baseline").eval()
    args = scene(size=32, n=1)
    with torch.no_grad():
        with pytest.raises(ValueError, match="budget must be"):
            model(*args, budget=GaussianBudget(0))
        with pytest.raises(ValueError, match="budget must be a fraction"):
            model(*args, budget=GaussianBudget(1.5))
        with pytest.raises(ValueError, match="rank_by must be one of"):
            model(*args, budget=GaussianBudget(0.5, rank_by="size"))
        with pytest.raises(ValueError, match="rank_by='learned' needs a model with an "
                                             "importance head"):
            model(*args, budget=GaussianBudget(0.5, rank_by="learned"))


def test_predict_takes_a_budget():
    torch.manual_seed(3)
    model = UniqueSplat.from_preset("tiny", variant="baseline", importance=True)
    args = scene(size=32, n=2)
    pred = model.predict(args.images[0], intrinsics=args.intrinsics[0],
                         extrinsics=args.extrinsics[0],
                         target_intrinsics=args.target_intrinsics[0],
                         target_extrinsics=args.target_extrinsics[0], near=1.0, far=100.0,
                         budget=100)
    assert [len(g) for g in pred.gaussians] == [100, 100]
    assert pred.color.shape == (2, 3, 32, 32) and model.training  # mode put back
