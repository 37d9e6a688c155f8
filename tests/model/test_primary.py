"""PrimaryNetwork: batches and views in the right order, input errors, gradients, and its
Gaussians through the rasteriser."""

import pytest
import torch

from tests.model.conftest import two_view_cameras
from usplat_dr.model import PrimaryNetwork, PrimaryNetworkCfg
from usplat_dr.render import RasterSettings, rasterize


def scene(b: int, v: int, size: int = 32, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    e, k = two_view_cameras(b, v)
    return (torch.rand(b, v, 3, size, size, generator=g), e, k, torch.ones(b, v),
            100 * torch.ones(b, v))


def test_batch_elements_are_independent(net):
    # (v b) bookkeeping: a batch of two scenes gives each scene's own Gaussians.
    s0, s1 = scene(1, 2, seed=1), scene(1, 2, seed=2)
    both = tuple(torch.cat([a, b]) for a, b in zip(s0, s1))
    with torch.no_grad():
        g, g0, g1 = net(*both), net(*s0), net(*s1)
    # 1e-4 relative: same float32 ops, batched vs not (different BLAS blocking).
    assert torch.allclose(g.means[0], g0.means[0], rtol=1e-4, atol=1e-4)
    assert torch.allclose(g.means[1], g1.means[0], rtol=1e-4, atol=1e-4)
    assert torch.allclose(g.harmonics[1], g1.harmonics[0], atol=1e-5)


def test_three_views_and_view_order(net):
    images, e, k, near, far = scene(1, 3)
    with torch.no_grad():
        g = net(images, e, k, near, far)
        perm = [2, 0, 1]
        gp = net(images[:, perm], e[:, perm], k[:, perm], near[:, perm], far[:, perm])
    assert g.means.shape == (1, 3 * 32 * 32, 3) and torch.isfinite(g.means).all()
    # Permuting the views permutes the Gaussians (cross-view attention and the mean over
    # the other views' cost volumes are symmetric); 1e-3: float32 sums in another order,
    # amplified by 1 / disparity.
    per_view = g.means.view(3, -1, 3)
    assert torch.allclose(gp.means.view(3, -1, 3), per_view[perm], rtol=1e-3, atol=1e-3)


def test_bad_inputs_name_the_argument(net):
    # check_inputs is what forward runs first (under pytest, jaxtyping's own shape check on
    # forward's annotations would fire before it for the shape case).
    images, e, k, near, far = scene(1, 2)
    with pytest.raises(ValueError, match="multiples of 16"):
        net(images[..., :24], e, k, near, far)
    with pytest.raises(ValueError, match=">= 2 context views"):
        net(images[:, :1], e[:, :1], k[:, :1], near[:, :1], far[:, :1])
    with pytest.raises(ValueError, match="extrinsics must have shape"):
        net.check_inputs(images, e[:, :, :3], k, near, far)
    with pytest.raises(ValueError, match="cost_volume_method"):
        PrimaryNetworkCfg(cost_volume_method="fast")
    with pytest.raises(ValueError, match="unknown PrimaryNetworkCfg keys"):
        PrimaryNetworkCfg.from_dict({"num_depth_candidate": 64})


def test_small_config_and_ablations_run_and_train():
    cfg = PrimaryNetworkCfg.from_dict({
        "num_depth_candidates": 16, "costvolume_unet_feat_dim": 32, "d_feature": 32,
        "num_transformer_layers": 2, "depth_unet_channel_mult": [1, 1, 1],
        "depth_unet_attn_res": [4], "sh_degree": 2, "use_cross_view_attention": False})
    net = PrimaryNetwork(cfg).train()
    g = net(*scene(1, 2))
    assert g.harmonics.shape == (1, 2 * 32 * 32, 3, 9)
    (g.means.square().mean() + g.harmonics.square().mean() + g.opacities.mean()
     + g.covariances.abs().mean()).backward()
    no_grad = [n for n, p in net.named_parameters() if p.grad is None]
    assert not no_grad, no_grad
    for switch in ("use_cost_volume", "use_cost_volume_refine", "use_depth_refine"):
        small = PrimaryNetwork(PrimaryNetworkCfg.from_dict({**cfg.__dict__, switch: False}))
        with torch.no_grad():
            assert torch.isfinite(small(*scene(1, 2)).means).all(), switch


def test_gaussians_render_with_mvsplats_basis(net):
    images, e, k, near, far = scene(1, 2)
    with torch.no_grad():
        g = net(images, e, k, near, far)
    out = rasterize(e[:, 0], k[:, 0], near[:, 0], far[:, 0], (32, 32), torch.zeros(1, 3),
                    g.means, g.covariances, g.harmonics, g.opacities,
                    RasterSettings(sh_basis="mvsplat"))
    assert out.color.shape == (1, 3, 32, 32) and torch.isfinite(out.color).all()
    assert out.alpha.mean() > 0.1  # the context view is covered by its own Gaussians
