"""Multi-view backbone: UniMatch's CNN and MVSplat's multi-view Swin-style transformer.

Key names and arithmetic follow MVSplat (``src/model/encoder/backbone/``) and UniMatch, so
official checkpoints and the UniMatch GMDepth backbone load strictly (docs/mvsplat_notes.md sec. 1).
"""

import math

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class ResidualBlock(nn.Module):
    """UniMatch residual block: conv3x3 -> InstanceNorm -> ReLU, twice, plus a (strided 1x1)
    shortcut; InstanceNorm without affine parameters, so it has no state-dict keys."""

    def __init__(self, in_planes: int, planes: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(in_planes, planes, 3, stride=stride, padding=1, bias=False)
        self.conv2 = nn.Conv2d(planes, planes, 3, padding=1, bias=False)
        self.norm1 = nn.InstanceNorm2d(planes)
        self.norm2 = nn.InstanceNorm2d(planes)
        self.downsample = None
        if stride != 1 or in_planes != planes:
            self.downsample = nn.Sequential(nn.Conv2d(in_planes, planes, 1, stride=stride),
                                            nn.InstanceNorm2d(planes))

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu(self.norm1(self.conv1(x)))
        y = F.relu(self.norm2(self.conv2(y)))
        if self.downsample is not None:
            x = self.downsample(x)
        return F.relu(x + y)


class CNNEncoder(nn.Module):
    """UniMatch ``CNNEncoder`` with ``num_output_scales=0``: 1/4 resolution, ``d_feature``
    channels (7x7/2 conv, 3 stages of 2 residual blocks at 64, 96, 128 channels, 1x1 conv)."""

    def __init__(self, d_feature: int = 128):
        super().__init__()
        dims = (64, 96, 128)
        self.conv1 = nn.Conv2d(3, dims[0], 7, stride=2, padding=3, bias=False)
        self.norm1 = nn.InstanceNorm2d(dims[0])
        block = ResidualBlock
        self.layer1 = nn.Sequential(block(dims[0], dims[0]), block(dims[0], dims[0]))
        self.layer2 = nn.Sequential(block(dims[0], dims[1], 2), block(dims[1], dims[1]))
        self.layer3 = nn.Sequential(block(dims[1], dims[2]), block(dims[2], dims[2]))
        self.conv2 = nn.Conv2d(dims[2], d_feature, 1)
        for m in self.modules():  # UniMatch's initialisation
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                if m.bias is not None:
                    nn.init.zeros_(m.bias)

    def forward(self, x: Float[Tensor, "n 3 h w"]) -> Float[Tensor, "n c h/4 w/4"]:
        x = F.relu(self.norm1(self.conv1(x)))
        return self.conv2(self.layer3(self.layer2(self.layer1(x))))


def split_windows(x: Tensor, splits: int) -> Tensor:
    """[N, H, W, C] -> [N * splits^2, H / splits, W / splits, C] (UniMatch ``split_feature``)."""
    n, h, w, c = x.shape
    x = x.view(n, splits, h // splits, splits, w // splits, c).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(n * splits * splits, h // splits, w // splits, c)


def merge_windows(x: Tensor, splits: int) -> Tensor:
    """Inverse of ``split_windows``."""
    nk, hs, ws, c = x.shape
    n = nk // (splits * splits)
    x = x.view(n, splits, splits, hs, ws, c).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(n, splits * hs, splits * ws, c)


def sine_position_embedding(h: int, w: int, channels: int, device=None) -> Tensor:
    """DETR's normalised sine embedding [channels, h, w]: y half first, then x (UniMatch
    ``PositionEmbeddingSine(num_pos_feats=channels // 2)``)."""
    npf = channels // 2
    scale, eps = 2 * math.pi, 1e-6
    y = torch.arange(1, h + 1, dtype=torch.float32, device=device)[:, None].expand(h, w)
    x = torch.arange(1, w + 1, dtype=torch.float32, device=device)[None, :].expand(h, w)
    y = y / (h + eps) * scale
    x = x / (w + eps) * scale
    dim_t = torch.arange(npf, dtype=torch.float32, device=device)
    dim_t = 10000 ** (2 * torch.div(dim_t, 2, rounding_mode="floor") / npf)
    pos_x, pos_y = x[..., None] / dim_t, y[..., None] / dim_t
    pos_x = torch.stack((pos_x[..., 0::2].sin(), pos_x[..., 1::2].cos()), dim=3).flatten(2)
    pos_y = torch.stack((pos_y[..., 0::2].sin(), pos_y[..., 1::2].cos()), dim=3).flatten(2)
    return torch.cat((pos_y, pos_x), dim=2).permute(2, 0, 1)


def add_window_position(x: Float[Tensor, "n c h w"], splits: int) -> Float[Tensor, "n c h w"]:
    """Add the sine embedding of one attention window to every window (UniMatch
    ``feature_add_position``): positions are relative to the window the token attends in."""
    n, c, h, w = x.shape  # noqa: RUF059 (unpacked to name the shape)
    pos = sine_position_embedding(h // splits, w // splits, c, x.device)
    return x + pos.repeat(1, splits, splits)[None]


def shifted_window_mask(h: int, w: int, splits: int, device=None) -> Tensor:
    """Swin attention mask [splits^2, L, L] (L = window tokens): 0 within a region, -100 across
    regions of the rolled image (UniMatch ``generate_shift_window_attn_mask``)."""
    wh, ww = h // splits, w // splits
    sh, sw = wh // 2, ww // 2
    img = torch.zeros(1, h, w, 1, device=device)
    cnt = 0
    for hs in (slice(0, -wh), slice(-wh, -sh), slice(-sh, None)):
        for ws in (slice(0, -ww), slice(-ww, -sw), slice(-sw, None)):
            img[:, hs, ws, :] = cnt
            cnt += 1
    win = split_windows(img, splits).view(-1, wh * ww)
    mask = win[:, None, :] - win[:, :, None]
    return mask.masked_fill(mask != 0, -100.0).masked_fill(mask == 0, 0.0)


class TransformerLayer(nn.Module):
    """UniMatch ``TransformerLayer``: single-head split-window attention, post-norm, optional
    FFN on concat(source, message); no biases on the linears."""

    def __init__(self, d_model: int = 128, ffn: bool = True, ffn_expansion: int = 4):
        super().__init__()
        self.q_proj = nn.Linear(d_model, d_model, bias=False)
        self.k_proj = nn.Linear(d_model, d_model, bias=False)
        self.v_proj = nn.Linear(d_model, d_model, bias=False)
        self.merge = nn.Linear(d_model, d_model, bias=False)
        self.norm1 = nn.LayerNorm(d_model)
        self.has_ffn = ffn
        if ffn:
            c = 2 * d_model
            self.mlp = nn.Sequential(nn.Linear(c, c * ffn_expansion, bias=False), nn.GELU(),
                                     nn.Linear(c * ffn_expansion, d_model, bias=False))
            self.norm2 = nn.LayerNorm(d_model)

    def forward(self, source: Tensor, targets: Tensor, hw: tuple[int, int], splits: int,
                mask: Tensor | None) -> Tensor:
        """``source`` [N, H*W, C] attends to ``targets`` [N, T, H*W, C] (T views whose keys are
        concatenated within each window); ``mask`` set for shifted windows."""
        n, length, c = source.shape
        t = targets.shape[1]
        h, w = hw
        q = self.q_proj(source).view(n, h, w, c)
        k = self.k_proj(targets).view(n * t, h, w, c)
        v = self.v_proj(targets).view(n * t, h, w, c)
        if mask is not None:
            shift = (-(h // splits // 2), -(w // splits // 2))
            q, k, v = (torch.roll(a, shifts=shift, dims=(1, 2)) for a in (q, k, v))
        k2 = splits * splits
        q = split_windows(q, splits).reshape(n * k2, -1, c)  # [N*K2, L, C]
        lw = q.shape[1]
        # [N*T*K2, L, C] -> [N, T, K2, L, C] -> [N*K2, T*L, C]: keys of all targets per window.
        k, v = (split_windows(a, splits).view(n, t, k2, lw, c).transpose(1, 2)
                .reshape(n * k2, t * lw, c) for a in (k, v))
        # softmax(q k^T / sqrt(C) + mask) v, fused (no [L, T*L] score matrix in memory).
        # (4-D inputs take torch's fused CPU kernel, 3x faster than the 3-D path here.)
        attn_mask = None if mask is None else mask.repeat(1, 1, t).repeat(n, 1, 1)[:, None]
        out = F.scaled_dot_product_attention(q[:, None], k[:, None], v[:, None],
                                             attn_mask=attn_mask)[:, 0]  # [N*K2, L, C]
        out = merge_windows(out.view(n * k2, h // splits, w // splits, c), splits)
        if mask is not None:
            out = torch.roll(out, shifts=(-shift[0], -shift[1]), dims=(1, 2))
        message = self.norm1(self.merge(out.reshape(n, length, c)))
        if self.has_ffn:
            message = self.norm2(self.mlp(torch.cat([source, message], dim=-1)))
        return source + message


class TransformerBlock(nn.Module):
    """Self-attention (no FFN), then cross-view attention with FFN. Without cross-view
    attention (MVSplat's Table 3 ablation) the self-attention layer carries the FFN."""

    def __init__(self, d_model: int = 128, ffn_expansion: int = 4, cross_view: bool = True):
        super().__init__()
        self.self_attn = TransformerLayer(d_model, ffn=not cross_view,
                                          ffn_expansion=ffn_expansion)
        if cross_view:
            self.cross_attn_ffn = TransformerLayer(d_model, ffn=True,
                                                   ffn_expansion=ffn_expansion)


class MultiViewTransformer(nn.Module):
    """MVSplat's multi-view feature transformer: ``num_layers`` blocks; odd blocks use shifted
    windows. A block's cross-view attention reads the other views' features as they were at
    the block's input (before its self-attention), as the reference does."""

    def __init__(self, num_layers: int = 6, d_model: int = 128, ffn_expansion: int = 4,
                 cross_view: bool = True):
        super().__init__()
        self.layers = nn.ModuleList(TransformerBlock(d_model, ffn_expansion, cross_view)
                                    for _ in range(num_layers))
        self.cross_view = cross_view
        for p in self.parameters():
            if p.dim() > 1:
                nn.init.xavier_uniform_(p)

    def forward(self, features: Float[Tensor, "b v c h w"], splits: int
                ) -> Float[Tensor, "b v c h w"]:
        b, v, c, h, w = features.shape
        if h % splits or w % splits or (splits > 1 and (h // splits) % 2 + (w // splits) % 2):
            raise ValueError(f"feature map {h}x{w} must split into {splits}x{splits} windows of "
                             f"even size: image height and width must be multiples of "
                             f"{8 * splits}")
        x = features.permute(0, 1, 3, 4, 2).reshape(b * v, h * w, c)  # [(b v), L, C]
        # Other views of each view, in cyclic order: [(b v), V-1, L, C].
        others = [[(i + j) % v for j in range(1, v)] for i in range(v)]
        mask = shifted_window_mask(h, w, splits, x.device) if splits > 1 else None
        for i, layer in enumerate(self.layers):
            m = mask if (splits > 1 and i % 2 == 1) else None
            targets = x.view(b, v, h * w, c)[:, others].reshape(b * v, v - 1, h * w, c)
            x = layer.self_attn(x, x[:, None], (h, w), splits, m)
            if self.cross_view:
                x = layer.cross_attn_ffn(x, targets, (h, w), splits, m)
        return x.view(b, v, h, w, c).permute(0, 1, 4, 2, 3)


class BackboneMultiview(nn.Module):
    """ImageNet-normalise, CNN per view, add window position embedding, transformer.
    Returns (transformer features, CNN features), both [B, V, C, H/4, W/4]."""

    def __init__(self, d_feature: int = 128, num_layers: int = 6, ffn_expansion: int = 4,
                 cross_view: bool = True):
        super().__init__()
        self.backbone = CNNEncoder(d_feature)
        self.transformer = MultiViewTransformer(num_layers, d_feature, ffn_expansion, cross_view)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(3, 1, 1), persistent=False)

    def forward(self, images: Float[Tensor, "b v 3 h w"], splits: int):
        b, v = images.shape[:2]
        x = ((images - self.mean) / self.std).flatten(0, 1)
        cnn = self.backbone(x)  # [(b v), C, h, w]
        trans = self.transformer(add_window_position(cnn, splits).unflatten(0, (b, v)), splits)
        return trans, cnn.unflatten(0, (b, v))
