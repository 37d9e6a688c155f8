"""train/studies/merge_then_drop.py: the cross-view pairs it finds, the moment matching of a
pair against the moments of the two-component mixture computed in float64, and the dither
budget that never keeps an emptied slot."""

import importlib.util
from pathlib import Path

import torch

from usplat_dr.model.types import Gaussians

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "merge_then_drop.py"
spec = importlib.util.spec_from_file_location("merge_then_drop", SCRIPT)
study = importlib.util.module_from_spec(spec)
spec.loader.exec_module(study)

H = W = 4


def two_views(offset: float = 0.01, seed: int = 0):
    """Two identical cameras at the origin looking down +z (so a view-0 Gaussian's partner is
    the view-1 Gaussian of the same pixel); view 0's Gaussians on the pixels' rays at depth 2,
    view 1's the same points moved by ``offset`` along x; random opacities and SH."""
    g = torch.Generator().manual_seed(seed)
    ys, xs = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    k = torch.tensor([[1.0, 0, 0.5], [0, 1, 0.5], [0, 0, 1]])
    rays = torch.stack([(xs / W - 0.5), (ys / H - 0.5), torch.ones_like(xs)], -1).view(-1, 3)
    view0 = 2 * rays
    view1 = view0 + torch.tensor([offset, 0, 0])
    means = torch.cat([view0, view1])[None]
    g_total = 2 * H * W
    gaussians = Gaussians(
        means=means, covariances=(0.01 * torch.eye(3)).expand(1, g_total, 3, 3).clone(),
        harmonics=torch.rand(1, g_total, 3, 4, generator=g),
        opacities=0.1 + 0.8 * torch.rand(1, g_total, generator=g),
        scales=torch.ones(1, g_total, 3), rotations=torch.zeros(1, g_total, 4))
    return gaussians, torch.eye(4).expand(1, 2, 4, 4), k.expand(1, 2, 3, 3)


def test_pairs_merge_within_the_bound_and_not_beyond():
    g, ext, k = two_views(offset=0.1)
    # Mahalanobis distance of the pair: 0.1^2 / (2 x 0.01) = 0.5
    partner, same = study.match_views(g.means, g.covariances, ext, k, H, W, chi2=1.0)
    assert torch.equal(partner[0], torch.arange(H * W)) and same.all()
    _, same = study.match_views(g.means, g.covariances, ext, k, H, W, chi2=0.4)
    assert not same.any()


def test_a_merged_pair_has_the_mixtures_moments_and_the_coverage_of_both():
    g, ext, k = two_views(offset=0.05)
    partner, same = study.match_views(g.means, g.covariances, ext, k, H, W, chi2=9.0)
    merged, emptied = study.merge_pairs(g, partner, same)
    hw = H * W
    assert torch.equal(emptied[0], torch.arange(2 * hw) >= hw)
    assert (merged.opacities[0, hw:] == 0).all()
    o0, o1 = g.opacities[0, :hw].double(), g.opacities[0, hw:].double()
    w0, w1 = o0 / (o0 + o1), o1 / (o0 + o1)
    m0, m1 = g.means[0, :hw].double(), g.means[0, hw:].double()
    mean = w0[:, None] * m0 + w1[:, None] * m1
    # the mixture's second moment E[x x^T] minus mean mean^T, each component's own moments
    second = (w0[:, None, None] * (g.covariances[0, :hw].double() + m0[:, :, None] * m0[:, None])
              + w1[:, None, None] * (g.covariances[0, hw:].double()
                                     + m1[:, :, None] * m1[:, None]))
    cov = second - mean[:, :, None] * mean[:, None]
    # float32 against float64: means of size ~2, covariances ~1e-2 (1e-6 is ~10 ulp of 2)
    assert torch.allclose(merged.means[0, :hw].double(), mean, atol=1e-6)
    assert torch.allclose(merged.covariances[0, :hw].double(), cov, atol=1e-6)
    assert torch.allclose(merged.opacities[0, :hw].double(), 1 - (1 - o0) * (1 - o1), atol=1e-6)
    sh = (w0[:, None, None] * g.harmonics[0, :hw].double()
          + w1[:, None, None] * g.harmonics[0, hw:].double())
    assert torch.allclose(merged.harmonics[0, :hw].double(), sh, atol=1e-6)


def test_one_view1_gaussian_merges_with_at_most_one_view0_gaussian():
    g, ext, k = two_views(offset=0.0)
    means = g.means.clone()
    means[0, 1] = means[0, 0] + torch.tensor([0.02, 0, 0])  # pixel 1 of view 0 moves onto pixel 0
    partner, same = study.match_views(means, g.covariances, ext, k, H, W, chi2=9.0)
    assert partner[0, 1] == partner[0, 0] == 0
    assert same[0, 0] and not same[0, 1]  # the closer one (distance 0) wins


def test_the_dither_budget_never_keeps_an_emptied_slot():
    g, ext, k = two_views(offset=0.05)
    partner, same = study.match_views(g.means, g.covariances, ext, k, H, W, chi2=9.0)
    merged, emptied = study.merge_pairs(g, partner, same)
    kept = study.dither_budget(merged, 0.5, (2, H, W, 1), emptied)
    assert kept.opacities.shape == (1, H * W) and (kept.opacities > 0).all()
