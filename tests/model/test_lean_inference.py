"""Inference without autograd takes a leaner path through the depth predictor (heads one view
at a time, GELUs in place, intermediates released early: the 2026-11-25 memory target). It must
compute what the autograd path computes, and ``import usplat_dr.model`` must not load the
Dr.Jit rasteriser for users of the primary network alone."""

import subprocess
import sys

import pytest
import torch
from torch import nn

from tests.model.conftest import inputs
from usplat_dr.model import PrimaryNetwork, PrimaryNetworkCfg
from usplat_dr.model.encoder.depth_predictor import (
    cat_channels_last,
    lean_head,
    lean_sequential,
)


def close(a: torch.Tensor, b: torch.Tensor) -> bool:
    # The lean path runs the same kernels on one view at a time; a convolution library may
    # pick another summation order for batch 1 than for batch 2 (oneDNN here does not: the
    # outputs are bit-identical on our CPUs), so allow float32 rounding of the largest value.
    return bool((a - b).abs().max() <= 1e-5 * max(1.0, b.abs().max().item()))


def test_lean_forward_equals_the_autograd_forward(net, fixture_dev):
    args = inputs(fixture_dev)
    with torch.no_grad():
        lean = net(*args)
    full = net(*args)  # autograd on: the batched heads, nothing released early
    assert full.means.requires_grad
    for name in ("means", "covariances", "harmonics", "opacities", "scales", "rotations"):
        assert close(getattr(lean, name), getattr(full, name).detach()), name


@pytest.mark.parametrize("use_depth_refine", [True, False])
def test_lean_depth_outputs_equal_the_autograd_ones(use_depth_refine):
    torch.manual_seed(0)
    cfg = PrimaryNetworkCfg.from_dict({
        "d_feature": 32, "num_transformer_layers": 1, "num_depth_candidates": 8,
        "costvolume_unet_feat_dim": 16, "use_depth_refine": use_depth_refine})
    small = PrimaryNetwork(cfg).eval()
    g = torch.Generator().manual_seed(1)
    e = torch.eye(4).repeat(2, 2, 1, 1)
    e[:, 1, 0, 3] = 0.2
    k = torch.tensor([[0.9, 0, 0.5], [0, 0.9, 0.5], [0, 0, 1]]).repeat(2, 2, 1, 1)
    args = (torch.rand(2, 2, 3, 32, 32, generator=g), e, k, torch.ones(2, 2),
            50 * torch.ones(2, 2))
    with torch.inference_mode():
        _, _, lean = small.encode(*args)
    _, _, full = small.encode(*args)
    for name in ("depths", "densities", "raw_gaussians", "raw_to_disparity", "head_input",
                 "features_fullres", "refine_out"):
        assert close(getattr(lean, name), getattr(full, name).detach()), name
    # the head input keeps its channels-last layout, and the features are a view of it
    assert lean.head_input.is_contiguous(memory_format=torch.channels_last)
    assert lean.features_fullres.data_ptr() > lean.head_input.data_ptr()
    assert lean.features_fullres.untyped_storage().data_ptr() == \
        lean.head_input.untyped_storage().data_ptr()
    lean.drop_intermediates()
    assert lean.head_input is None and lean.features_fullres is None and lean.refine_out is None


def test_cat_channels_last_is_cat_then_channels_last_with_type_promotion():
    g = torch.Generator().manual_seed(0)
    parts = (torch.randn(2, 3, 5, 7, generator=g).to(torch.bfloat16),
             torch.randn(2, 1, 5, 7, generator=g),
             torch.randn(2, 4, 5, 7, generator=g).contiguous(memory_format=torch.channels_last))
    out = cat_channels_last(parts)
    ref = torch.cat(parts, dim=1).contiguous(memory_format=torch.channels_last)
    assert out.dtype == ref.dtype == torch.float32
    assert out.is_contiguous(memory_format=torch.channels_last)
    assert torch.equal(out, ref)  # copies only: exact


def test_lean_sequential_and_head_leave_their_input_alone():
    torch.manual_seed(0)
    seq = nn.Sequential(nn.GELU(), nn.Conv2d(4, 6, 3, padding=1), nn.GELU(),
                        nn.Conv2d(6, 2, 3, padding=1), nn.GELU(approximate="tanh"))
    x = torch.randn(3, 4, 8, 8)
    before = x.clone()
    with torch.no_grad():
        ref = seq(x)
        assert torch.equal(x, before)
        out = lean_sequential(seq, x)
        assert torch.equal(x, before)  # the leading GELU is not applied in place
        assert close(out, ref)
        head = lean_head(seq, x)
        assert torch.equal(x, before) and close(head, ref)
        assert head.is_contiguous()  # channels-first in, channels-first out
        xc = x.contiguous(memory_format=torch.channels_last)
        head_cl = lean_head(seq, xc)
        assert head_cl.is_contiguous(memory_format=torch.channels_last) and close(head_cl, ref)


def test_importing_the_model_package_leaves_the_rasteriser_unloaded():
    code = ("import sys, usplat_dr.model as m; assert 'drjit' not in sys.modules; "
            "m.PrimaryNetwork; assert 'drjit' not in sys.modules; "
            "from usplat_dr.model import UniqueSplat, PRESETS; assert 'drjit' in sys.modules; "
            "assert 'tiny' in PRESETS and 'UniqueSplat' in dir(m)")
    subprocess.run([sys.executable, "-c", code], check=True)
    import usplat_dr.model as m

    with pytest.raises(AttributeError, match="no attribute 'Nope'"):
        m.Nope  # noqa: B018
