"""Run a head (convolutions with GELU between them) with weights W + Delta W per target view:
all targets in one batched operation per layer (convolutions grouped by scene or target,
batched matrix products), and everything before the first layer with a Delta W once per scene.

An activation is either scene-level, [(V B), C, H, W] channels-last (the depth predictor's
(v b) order), or per target, [B, N, V, H, W, C] contiguous (the Gaussian adapter's order).
"""

import torch
import torch.nn.functional as F
from torch import Tensor

from usplat_dr.model.hypernet.hypernetwork import LayerDelta

CL = torch.channels_last


def _grouped(x: Tensor, per_target: bool, v: int, b: int, n: int) -> Tensor:
    """The input of a convolution grouped by scene (scene-level ``x``) or by target
    (per-target ``x``): [V, (G C), H, W] channels-last, i.e. memory [V, H, W, G, C]."""
    if per_target:
        _, _, _, h, w, c = x.shape
        t = x.permute(2, 3, 4, 0, 1, 5)  # [V, H, W, B, N, C]
        return t.reshape(v, h, w, b * n * c).permute(0, 3, 1, 2)
    _, c, h, w = x.shape
    if b == 1:
        return x.view(v, c, h, w)
    return x.view(v, b, c, h, w).permute(0, 3, 4, 1, 2).reshape(v, h, w, b * c).permute(
        0, 3, 1, 2)


def _to_targets(t: Tensor, b: int, n: int) -> Tensor:
    """[V, H, W, (B N), C] -> [B, N, V, H, W, C] contiguous."""
    v, h, w, _, c = t.shape
    return t.view(v, h, w, b, n, c).permute(3, 4, 0, 1, 2, 5).contiguous()


def injected_conv(x: Tensor, per_target: bool, weight: Tensor, bias: Tensor,
                  delta: LayerDelta | None, v: int, b: int, n: int) -> tuple[Tensor, bool]:
    """One convolution with weight ``weight`` + Delta W (per target; ``None``: no Delta W).

    ``x`` is scene-level when ``per_target`` is False, per target otherwise (module
    docstring). Returns the output and whether it is per target."""
    o, i, k, _ = weight.shape
    pad = k // 2
    if delta is None and not per_target:
        return F.conv2d(x, weight, bias, padding=pad), False
    groups = b * n if per_target else b
    xin = _grouped(x, per_target, v, b, n)
    h, w = xin.shape[-2:]
    if delta is None:  # the same weights for every target
        y = F.conv2d(xin, weight.repeat(groups, 1, 1, 1), bias.repeat(groups), padding=pad,
                     groups=groups)
        return _to_targets(y.permute(0, 2, 3, 1).reshape(v, h, w, b * n, o), b, n), True
    if delta.full is not None:  # full-rank Delta W: one convolution grouped by target
        if delta.bias.ndim != 2:
            raise ValueError(f"a full Delta W takes a bias change per target [B N, O], got "
                             f"{list(delta.bias.shape)} (a bias per context view needs the "
                             f"rank-r form)")
        if not per_target:  # each scene's input once per target
            xin = xin.permute(0, 2, 3, 1).view(v, h, w, b, 1, i).expand(v, h, w, b, n, i)
            xin = xin.reshape(v, h, w, b * n * i).permute(0, 3, 1, 2)
        wt = (weight + delta.full).reshape(b * n * o, i, k, k)
        y = F.conv2d(xin, wt, (bias + delta.bias).reshape(-1), padding=pad, groups=b * n)
        return _to_targets(y.permute(0, 2, 3, 1).reshape(v, h, w, b * n, o), b, n), True
    # Rank r: conv(x, W + U V) = conv(x, W) + U conv(x, V). The base and the V-convolutions
    # run as one convolution (grouped by scene, or by target once x is per target), then
    # U mixes the r channels per target in one batched matrix product.
    r = delta.u.shape[-1]
    vw = delta.v.reshape(groups, -1, i, k, k)  # [G, (N r) or r, I, k, k]
    wt = torch.cat((weight[None].expand(groups, o, i, k, k), vw), 1).reshape(-1, i, k, k)
    y = F.conv2d(xin, wt, padding=pad, groups=groups)
    y = y.permute(0, 2, 3, 1).reshape(v, h * w, groups, -1)  # [V, HW, G, O + ..]
    z = y[..., o:].reshape(v * h * w, b * n, r).transpose(0, 1)  # [B N, V H W, r]
    out = torch.bmm(z, delta.u.transpose(1, 2))  # [B N, V H W, O]
    base = y[..., :o].permute(2, 0, 1, 3)  # [G, V, HW, O]
    out = out.view(b, n, v, h * w, o)
    if per_target:
        out += base.reshape(b, n, v, h * w, o)
    else:
        out += base[:, None]
    if delta.bias.ndim == 3:  # a bias change per (target, context view): [B N, V, O]
        out += (bias + delta.bias).view(b, n, v, 1, o)
    else:
        out += (bias + delta.bias).view(b, n, 1, 1, o)
    return out.view(b, n, v, h, w, o), True


def run_head(x: Tensor, layers: list[tuple[Tensor, Tensor, LayerDelta | None]], v: int,
             b: int, n: int) -> tuple[Tensor, bool]:
    """Convolutions with GELU between them (MVSplat's two-layer heads) on the scene-level
    ``x`` [(V B), C, H, W]; returns the output and whether it is per target."""
    per_target = False
    for j, (w, bias, delta) in enumerate(layers):
        if j:
            x = F.gelu(x)
        x, per_target = injected_conv(x, per_target, w, bias, delta, v, b, n)
    return x, per_target


def adapter_layout(y: Tensor, per_target: bool, v: int, b: int, n: int) -> Tensor:
    """A head's output as [(B N), V, H*W, C] (the Gaussian adapter's layout); a scene-level
    output is repeated over the targets."""
    if per_target:
        return y.view(b * n, v, -1, y.shape[-1])
    _, c, h, w = y.shape
    t = y.view(v, b, c, h * w).permute(1, 0, 3, 2)  # [B, V, HW, C]
    return t[:, None].expand(b, n, v, h * w, c).reshape(b * n, v, h * w, c)


def vb_layout(y: Tensor, per_target: bool, v: int, b: int, n: int) -> Tensor:
    """A head's output as [(V B N), C, H, W] (the depth head's (v b) layout with B N
    batches); a scene-level output is repeated over the targets."""
    if per_target:
        _, _, _, h, w, c = y.shape
        return y.permute(2, 0, 1, 5, 3, 4).reshape(v * b * n, c, h, w)
    _, c, h, w = y.shape
    return y.view(v, b, 1, c, h, w).expand(v, b, n, c, h, w).reshape(v * b * n, c, h, w)
