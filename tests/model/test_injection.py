"""W + Delta W per target, batched: ``run_head`` against a float64 loop over scenes and targets
that builds every target's full weight from the equations and calls conv2d on it."""

import math

import pytest
import torch
import torch.nn.functional as F

from usplat_dr.model.hypernet.hypernetwork import (
    AgnosticHypernetwork,
    ConvSpec,
    LayerDelta,
    SpecificHypernetwork,
    split_deltas,
    weights_size,
)
from usplat_dr.model.hypernet.injection import adapter_layout, run_head, vb_layout


def reference(x, layers, v, b, n):
    """[B, N, V, C, H, W]: each target's head with its own full weights, one at a time."""
    x = x.view(v, b, *x.shape[1:])
    rows = []
    for bi in range(b):
        for ni in range(n):
            y = x[:, bi]
            for j, (w, bias, d) in enumerate(layers):
                if j:
                    y = F.gelu(y)
                wt, bt = w, bias
                if d is not None:
                    dw = d.full[bi * n + ni] if d.full is not None else (
                        d.u[bi * n + ni] @ d.v[bi * n + ni].flatten(1)).view_as(w)
                    wt, bt = w + dw, bias + d.bias[bi * n + ni]
                if bt.ndim == 2:  # a bias per context view [V, O]: one conv per view
                    y = torch.cat([F.conv2d(y[vi:vi + 1], wt, bt[vi], padding=w.shape[-1] // 2)
                                   for vi in range(v)])
                else:
                    y = F.conv2d(y, wt, bt, padding=w.shape[-1] // 2)
            rows.append(y)
    return torch.stack(rows).view(b, n, v, *rows[0].shape[1:])


def make(spec_io, rank, which, b, n, gen):
    layers = []
    for j, (o, i) in enumerate(spec_io):
        w = torch.randn(o, i, 3, 3, generator=gen, dtype=torch.float64) / math.sqrt(9 * i)
        bias = torch.randn(o, generator=gen, dtype=torch.float64)
        d = None
        if j in which:
            db = torch.randn(b * n, o, generator=gen, dtype=torch.float64)
            if rank is None:
                d = LayerDelta(bias=db, full=0.1 * torch.randn(b * n, o, i, 3, 3, generator=gen,
                                                               dtype=torch.float64))
            else:
                d = LayerDelta(bias=db, u=torch.randn(b * n, o, rank, generator=gen,
                                                      dtype=torch.float64),
                               v=0.1 * torch.randn(b * n, rank, i, 3, 3, generator=gen,
                                                   dtype=torch.float64))
        layers.append((w, bias, d))
    return layers


@pytest.mark.parametrize("rank", [3, None])
@pytest.mark.parametrize("which", [(1,), (0,), (0, 1), ()])
@pytest.mark.parametrize("b", [1, 2])
def test_run_head_matches_per_target_convolutions(rank, which, b):
    # float64 both sides: the batched path reorders sums (grouped conv, bmm) only, so the
    # difference is rounding, ~1e-15 relative; 1e-10 leaves room and would catch any
    # misplaced target, scene or channel (errors of order 1).
    v, n, h, w = 2, 3, 5, 7
    gen = torch.Generator().manual_seed(hash((rank, which, b)) % 2**31)
    x = torch.randn(v * b, 6, h, w, generator=gen, dtype=torch.float64)
    layers = make([(8, 6), (4, 8)], rank, which, b, n, gen)
    y, per_target = run_head(x.contiguous(memory_format=torch.channels_last), layers, v, b, n)
    assert per_target == bool(which)
    ref = reference(x, layers, v, b, n)  # [B, N, V, C, H, W]
    got = adapter_layout(y, per_target, v, b, n)  # [(B N), V, HW, C]
    assert torch.allclose(got, ref.flatten(0, 1).flatten(-2).transpose(-1, -2), rtol=1e-10,
                          atol=1e-10)
    got_vb = vb_layout(y, per_target, v, b, n)  # [(V B N), C, H, W]
    assert torch.allclose(got_vb, ref.permute(2, 0, 1, 3, 4, 5).flatten(0, 2), rtol=1e-10,
                          atol=1e-10)


def test_hypernetworks_start_at_the_base_weights_and_zero_delta():
    specs = (ConvSpec("to_gaussians.0", 8, 6, 3), ConvSpec("to_gaussians.2", 4, 8, 3))
    base = torch.randn(weights_size(specs))
    agnostic = AgnosticHypernetwork(specs, 16, 8, base)
    w = agnostic()
    assert torch.equal(torch.cat([t.reshape(-1) for pair in w for t in pair]), base)
    for rank in (2, None):
        specific = SpecificHypernetwork(specs, 16, 8, rank)
        deltas = specific(torch.randn(5, 16))
        for d, s in zip(deltas, specs):
            dw = d.full if rank is None else d.u @ d.v.flatten(2)
            assert not dw.any() and not d.bias.any()
            if rank is not None:  # V is not zero, so U gets a gradient from the first step
                assert d.v.abs().sum() > 0 and d.v.shape == (5, rank, s.in_channels, 3, 3)
    with pytest.raises(ValueError, match="base weights must have"):
        agnostic.set_base(torch.zeros(3))


def test_split_deltas_layout():
    specs = (ConvSpec("a", 3, 2, 1),)
    flat = torch.arange(3 * 2 + 2 * 2 + 3, dtype=torch.float32)[None]
    (d,) = split_deltas(flat, specs, rank=2)
    # u first (O r), then v (r I k k, scaled by 1/sqrt(fan_in = 2)), then the bias delta
    assert d.u.tolist() == [[[0, 1], [2, 3], [4, 5]]]
    assert torch.allclose(d.v.flatten(), torch.tensor([6.0, 7, 8, 9]) / math.sqrt(2))
    assert d.bias.tolist() == [[10, 11, 12]]


@pytest.mark.parametrize("b", [1, 2])
def test_a_bias_per_target_and_context_view(b):
    # The oracle's probe: a bias change per (target, context view) on the last layer, against
    # the float64 loop that adds each view's own bias (tolerance as above).
    v, n, h, w = 2, 3, 4, 5
    gen = torch.Generator().manual_seed(7 + b)
    x = torch.randn(v * b, 6, h, w, generator=gen, dtype=torch.float64)
    layers = make([(8, 6), (4, 8)], 2, (1,), b, n, gen)
    _wt, _bias, d = layers[1]
    d.bias = torch.randn(b * n, v, 4, generator=gen, dtype=torch.float64)
    y, per_target = run_head(x.contiguous(memory_format=torch.channels_last), layers, v, b, n)
    ref = reference(x, layers, v, b, n)
    got = adapter_layout(y, per_target, v, b, n)
    assert torch.allclose(got, ref.flatten(0, 1).flatten(-2).transpose(-1, -2), rtol=1e-10,
                          atol=1e-10)
    # the views' biases matter: the same bias for both views gives another output
    d.bias = d.bias[:, :1].expand(b * n, v, 4)
    other = adapter_layout(run_head(x.contiguous(memory_format=torch.channels_last), layers,
                                    v, b, n)[0], True, v, b, n)
    assert not torch.allclose(other, got, atol=1e-3)
    d.full, d.u, d.v = torch.zeros(b * n, 4, 8, 3, 3, dtype=torch.float64), None, None
    with pytest.raises(ValueError, match="bias change per target"):
        run_head(x.contiguous(memory_format=torch.channels_last), layers, v, b, n)
