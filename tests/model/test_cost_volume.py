"""Plane sweep: the fast dot-product form equals the warping form and a dense float64
reference written from the equations (integer pixel coordinates, bilinear with zero
padding, the reference view's K for both projections)."""

import torch

from usplat_dr.model.encoder.cost_volume import disparity_candidates, plane_sweep_correlation


def cameras(b: int, v: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    e = torch.eye(4).repeat(b, v, 1, 1)
    e[..., :3, 3] = 0.15 * torch.randn(b, v, 3, generator=g)
    angle = 0.05 * torch.randn(b, v, generator=g)
    e[..., 0, 0], e[..., 0, 2] = angle.cos(), angle.sin()
    e[..., 2, 0], e[..., 2, 2] = -angle.sin(), angle.cos()
    k = torch.tensor([[0.8, 0, 0.5], [0, 0.9, 0.5], [0, 0, 1]]).repeat(b, v, 1, 1)
    return e, k


def dense_reference(feat, e, k_norm, disp):
    """float64 loops over views and candidates; bilinear sampling by hand."""
    feat, e, k_norm, disp = feat.double(), e.double(), k_norm.double(), disp.double()
    b, v, c, h, w = feat.shape
    out = torch.zeros(v * b, disp.shape[1], h, w, dtype=torch.float64)
    ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    pix = torch.stack([xs, ys, torch.ones_like(xs)], -1).double().view(-1, 3)  # [HW, 3]
    for bi in range(b):
        for vi in range(v):
            k = k_norm[bi, vi].clone()
            k[0] *= w
            k[1] *= h
            for oi in (o for o in range(v) if o != vi):
                pose = torch.linalg.inv(e[bi, oi]) @ e[bi, vi]
                for di in range(disp.shape[1]):
                    depth = 1 / disp[vi * b + bi, di]
                    p = (pose[:3, :3] @ (torch.linalg.inv(k) @ pix.T) * depth) + pose[:3, 3:]
                    q = k @ p
                    x, y = q[0] / q[2].clamp(min=1e-3), q[1] / q[2].clamp(min=1e-3)
                    x0, y0 = x.floor(), y.floor()
                    sample = torch.zeros(c, h * w, dtype=torch.float64)
                    for dx in (0, 1):
                        for dy in (0, 1):
                            xi, yi = x0 + dx, y0 + dy
                            wgt = (1 - (x - xi).abs()) * (1 - (y - yi).abs())
                            ok = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
                            idx = (yi.clamp(0, h - 1) * w + xi.clamp(0, w - 1)).long()
                            sample += feat[bi, oi].reshape(c, -1)[:, idx] * (wgt * ok)
                    corr = (feat[bi, vi].reshape(c, -1) * sample).sum(0) / c**0.5
                    out[vi * b + bi, di] += corr.view(h, w) / (v - 1)
    return out


def test_gram_warp_and_dense_reference_agree():
    b, v, c, h, w = 2, 3, 8, 6, 7
    feat = torch.randn(b, v, c, h, w, generator=torch.Generator().manual_seed(0))
    e, k = cameras(b, v, 1)
    disp = disparity_candidates(torch.full((b, v), 0.5), torch.full((b, v), 20.0), 12)
    ref = dense_reference(feat, e, k, disp)
    gram = plane_sweep_correlation(feat, e, k, disp, "gram", max_bytes=200)  # many row chunks
    warp = plane_sweep_correlation(feat, e, k, disp, "warp", chunk=5)
    # float32 sums of 8 products of O(1) values, and coordinates rounded in float32 near
    # pixel edges: 1e-4 absolute on values of O(3).
    assert (gram.double() - ref).abs().max() < 1e-4
    assert (warp.double() - ref).abs().max() < 1e-4
    assert ref.abs().max() > 1  # not a trivially zero volume


def test_gram_gradients_match_warp():
    b, v, c, h, w = 1, 2, 4, 5, 6
    e, k = cameras(b, v, 2)
    disp = disparity_candidates(torch.full((b, v), 0.5), torch.full((b, v), 20.0), 6)
    grads = []
    for method in ("gram", "warp"):
        feat = torch.randn(b, v, c, h, w, generator=torch.Generator().manual_seed(3),
                           requires_grad=True)
        plane_sweep_correlation(feat, e, k, disp, method).square().sum().backward()
        grads.append(feat.grad)
    assert torch.allclose(grads[0], grads[1], atol=1e-4)  # float32, values of O(10)
