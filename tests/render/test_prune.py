"""Per-target pruning (``usplat_dr.render.prune``) against the dense float64 reference
renderer (``usplat_dr.render.reference``): exact culling drops only Gaussians that render
nothing, merging follows the moment-matching equations, the footprint scores (the budget's
``"footprint"`` ranking) are opacity x screen area where the culling keeps a Gaussian."""

import math

import numpy as np
import pytest
import torch

from usplat_dr.render import RasterSettings, rasterize
from usplat_dr.render.prune import PruneSettings, footprint_scores, prune, screen_footprint
from usplat_dr.render.reference import project_ref, render_ref


def random_scene(seed=0, b=2, g=1500, shape=(48, 64)):
    """Gaussians spread well beyond the frustum, some behind the camera, opacities skewed low."""
    gen = torch.Generator().manual_seed(seed)
    ext = torch.eye(4).repeat(b, 1, 1)
    ext[1, :3, 3] = torch.tensor([0.3, -0.1, 0.2])
    k = torch.tensor([[0.8, 0, 0.52], [0, 1.0, 0.47], [0, 0, 1]]).repeat(b, 1, 1)
    near, far = torch.full((b,), 0.5), torch.full((b,), 20.0)
    means = (torch.randn(b, g, 3, generator=gen) * torch.tensor([3.0, 3.0, 2.0])
             + torch.tensor([0, 0, 3.0]))
    a = torch.randn(b, g, 3, 3, generator=gen) * 0.05
    cov = a @ a.transpose(-1, -2) + 1e-4 * torch.eye(3)
    sh = torch.randn(b, g, 3, 4, generator=gen) * 0.3
    op = torch.rand(b, g, generator=gen) ** 2
    return ext, k, near, far, shape, means, cov, sh, op


def test_screen_footprint_matches_reference_projection():
    ext, k, near, _, (h, w), means, cov, _, _ = random_scene()
    fp = screen_footprint(ext, k, near, (h, w), means, cov)
    for bi in range(2):
        u, v, _, _, radius, valid = project_ref(ext[bi].double(), k[bi].double(), near[bi], w,
                                                h, means[bi].double(), cov[bi].double())
        assert torch.equal(fp["valid"][bi], valid)
        m = valid
        # float32 against float64 projection of points up to ~10 units away: ~1e-5 px
        assert torch.allclose(fp["u"][bi][m].double(), u[m], atol=1e-3)
        assert torch.allclose(fp["v"][bi][m].double(), v[m], atol=1e-3)
        # the radius is a ceil(): float32 rounding may move it by one pixel at an integer
        assert (fp["radius"][bi][m].double() - radius[m]).abs().max() <= 1


def test_cull_keeps_the_render_and_drops_only_invisible_gaussians():
    ext, k, near, far, shape, means, cov, sh, op = random_scene()
    bg = torch.zeros(2, 3)
    p = prune(ext, k, near, shape, means, cov, sh, op, PruneSettings())
    assert (p.counts < 0.6 * means.shape[1]).all()  # the scene is built to be mostly unseen
    full = rasterize(ext, k, near, far, shape, bg, means, cov, sh, op, RasterSettings())
    cut = rasterize(ext, k, near, far, shape, bg, p.means, p.covariances, p.harmonics,
                    p.opacities, RasterSettings())
    # the same Gaussians composited in the same depth order: only float32 summation order
    # could differ (it does not here; 1e-6 leaves room for it)
    for a, b in ((full.color, cut.color), (full.alpha, cut.alpha), (full.depth, cut.depth)):
        assert (a - b).abs().max() <= 1e-6
    # independent check: every dropped Gaussian, rendered alone by the dense float64
    # reference, covers no pixel at all
    for bi in range(2):
        kept = {tuple(x) for x in p.means[bi, :p.counts[bi]].tolist()}
        dropped = torch.tensor([i for i, x in enumerate(means[bi].tolist())
                                if tuple(x) not in kept])
        assert len(dropped) == means.shape[1] - p.counts[bi]
        for chunk in dropped.split(200):
            n = len(chunk)
            _, alpha, _ = render_ref(
                ext[bi:bi + 1].double().expand(n, 4, 4), k[bi:bi + 1].double().expand(n, 3, 3),
                near[bi:bi + 1].double().expand(n), far[bi:bi + 1].double().expand(n), shape,
                torch.zeros(n, 3, dtype=torch.float64), means[bi, chunk, None].double(),
                cov[bi, chunk, None].double(), sh[bi, chunk, None].double(),
                op[bi, chunk, None].double())
            assert alpha.abs().max() == 0


def test_cull_cases_by_construction():
    """One Gaussian per case in front of an identity camera (64x64, fov 90 degrees)."""
    ext, k = torch.eye(4)[None], torch.tensor([[[0.5, 0, 0.5], [0, 0.5, 0.5], [0, 0, 1.0]]])
    near = torch.tensor([1.0])
    means = torch.tensor([[[0.0, 0, 5], [0, 0, -5], [0, 0, 0.1], [0, 0, 5], [40, 0, 5],
                           [5.3, 0, 5]]])
    # case: visible, behind, in front of 0.2 near, opacity 1e-3, far outside, centre just
    # outside the right edge (x/z = 1.06: 2 px) but wide enough to reach into the image
    cov = torch.eye(3).expand(1, 6, 3, 3) * torch.tensor([0.01, 0.01, 0.01, 0.01, 0.01, 0.05]
                                                         )[None, :, None, None]
    op = torch.tensor([[0.9, 0.9, 0.9, 1e-3, 0.9, 0.9]])
    sh = torch.zeros(1, 6, 3, 1)
    p = prune(ext, k, near, (64, 64), means, cov, sh, op, PruneSettings())
    assert p.counts.tolist() == [2]
    assert torch.equal(p.means[0], means[0, [0, 5]])


def test_merge_follows_moment_matching():
    """Two near-duplicates (as from two context views) and one far away; a different colour
    at the duplicates' place stays separate. The merged Gaussian against float64 equations."""
    ext, k = torch.eye(4)[None], torch.tensor([[[0.5, 0, 0.5], [0, 0.5, 0.5], [0, 0, 1.0]]])
    near = torch.tensor([1.0])
    # pixel size at z = 4 with f = 32 px: 0.125; the pair is 0.01 apart, same depth bin
    means = torch.tensor([[[0.062, 0.062, 4.0], [0.07, 0.065, 4.01], [1.0, 1.0, 4.0],
                           [0.064, 0.063, 4.0]]])
    rng = np.random.default_rng(0)
    a = rng.normal(size=(4, 3, 3)) * 0.02
    cov = torch.tensor(a @ a.transpose(0, 2, 1) + 1e-4 * np.eye(3), dtype=torch.float32)[None]
    sh = torch.zeros(1, 4, 3, 4)
    sh[0, :, :, 1:] = torch.tensor(rng.normal(size=(4, 3, 3)) * 0.1, dtype=torch.float32)
    sh[0, :3, :, 0] = 0.3  # colour 0.585: one colour bin
    sh[0, 3, :, 0] = -1.0  # colour 0.218: another
    op = torch.tensor([[0.6, 0.3, 0.8, 0.7]])
    p = prune(ext, k, near, (64, 64), means, cov, sh, op, PruneSettings(merge=True))
    assert p.counts.tolist() == [3]
    i = int(torch.argmin((p.opacities[0] - (1 - 0.4 * 0.7)).abs()))
    o = op[0, :2].double()
    w = o / o.sum()
    m = (w[:, None] * means[0, :2].double()).sum(0)
    d = means[0, :2].double() - m
    c = sum(w[j] * (cov[0, j].double() + torch.outer(d[j], d[j])) for j in range(2))
    s = (w[:, None, None] * sh[0, :2].double()).sum(0)
    # float32 arithmetic on values of order 1: relative 1e-6
    assert p.opacities[0, i].item() == pytest.approx(1 - 0.4 * 0.7, abs=1e-6)
    assert torch.allclose(p.means[0, i].double(), m, atol=1e-6)
    assert torch.allclose(p.covariances[0, i].double(), c, atol=1e-7)
    assert torch.allclose(p.harmonics[0, i].double(), s, atol=1e-6)
    others = {tuple(x) for x in p.means[0].tolist()} - {tuple(p.means[0, i].tolist())}
    assert others == {tuple(means[0, 2].tolist()), tuple(means[0, 3].tolist())}


def test_merging_duplicates_keeps_the_image():
    """A scene rendered from two copies of itself with jittered positions (two views seeing
    one surface): merging halves the count and keeps the image close to the original."""
    gen = torch.Generator().manual_seed(1)
    ext, k = torch.eye(4)[None], torch.tensor([[[0.7, 0, 0.5], [0, 0.7, 0.5], [0, 0, 1.0]]])
    near, far = torch.tensor([1.0]), torch.tensor([20.0])
    n = 800
    xy = torch.rand(n, 2, generator=gen) * 2.4 - 1.2
    base = torch.cat([xy, torch.full((n, 1), 4.0)], -1)
    jitter = torch.randn(n, 3, generator=gen) * 0.002
    means = torch.cat([base, base + jitter])[None]
    cov = (torch.eye(3) * torch.tensor([0.004, 0.004, 1e-5]))[None, None].expand(1, 2 * n, 3, 3)
    colour = torch.rand(n, 3, generator=gen)
    sh = ((torch.cat([colour, colour]) - 0.5) / 0.28209479177387814)[None, :, :, None]
    op = torch.full((1, 2 * n), 0.5)
    bg = torch.zeros(1, 3)
    shape = (64, 64)
    ref = rasterize(ext, k, near, far, shape, bg, means, cov, sh, op)
    p = prune(ext, k, near, shape, means, cov, sh, op, PruneSettings(merge=True))
    got = rasterize(ext, k, near, far, shape, bg, p.means, p.covariances, p.harmonics,
                    p.opacities)
    assert p.counts.item() < 1.3 * n  # most pairs share a cell (grid borders split some)
    mse = (got.color - ref.color).square().mean().item()
    # moment matching keeps coverage at the centres; the tails differ (1 - (1 - o g)^2 vs
    # (1 - (1 - o)^2) g): measured 35 dB here, 30 dB leaves margin and still fails for
    # dropping one of each pair (about 20 dB)
    assert -10 * math.log10(mse) > 30


def test_footprint_scores_are_opacity_times_area_where_visible():
    ext, k, near, _, shape, means, cov, sh, op = random_scene()
    scores = footprint_scores(ext, k, near, shape, means, cov, op)
    full = prune(ext, k, near, shape, means, cov, sh, op, PruneSettings())
    for bi in range(2):
        # culled ones score -1: exactly those that culling drops
        visible = {tuple(x) for x in full.means[bi, :full.counts[bi]].tolist()}
        kept = [tuple(x) in visible for x in means[bi].tolist()]
        assert torch.equal(scores[bi] >= 0, torch.tensor(kept))
        assert (scores[bi][~torch.tensor(kept)] == -1).all()
        # float64 importance from the reference projection: opacity x 3-sigma ellipse area
        _, _, conic, _, _, _ = project_ref(ext[bi].double(), k[bi].double(), near[bi], shape[1],
                                           shape[0], means[bi].double(), cov[bi].double())
        det2 = 1 / (conic[:, 0] * conic[:, 2] - conic[:, 1] ** 2)
        ref = op[bi].double() * (9 * math.pi * det2.sqrt()).clamp(max=shape[0] * shape[1])
        mask = torch.tensor(kept)
        # float32 projection against float64: 1e-4 relative covers the 2D covariance's
        # rounding (the scores span orders of magnitude; a wrong area factor is off by >= 2x)
        assert torch.allclose(scores[bi][mask].double(), ref[mask], rtol=1e-4, atol=0)


def test_padding_renders_each_entry_as_alone():
    ext, k, near, far, shape, means, cov, sh, op = random_scene(seed=3)
    p = prune(ext, k, near, shape, means, cov, sh, op, PruneSettings())
    assert p.counts[0] != p.counts[1]
    bg = torch.zeros(2, 3)
    both = rasterize(ext, k, near, far, shape, bg, p.means, p.covariances, p.harmonics,
                     p.opacities)
    for bi in range(2):
        c = p.counts[bi]
        one = rasterize(ext[bi:bi + 1], k[bi:bi + 1], near[bi:bi + 1], far[bi:bi + 1], shape,
                        bg[:1], p.means[bi:bi + 1, :c], p.covariances[bi:bi + 1, :c],
                        p.harmonics[bi:bi + 1, :c], p.opacities[bi:bi + 1, :c])
        assert (one.color[0] - both.color[bi]).abs().max() <= 1e-6  # see the cull test


def test_settings_are_checked():
    with pytest.raises(ValueError, match="retired.*GaussianBudget.*footprint"):
        PruneSettings(keep_fraction=0.5)
    with pytest.raises(ValueError, match="merge_pixels"):
        PruneSettings(merge_pixels=-1.0)
