"""MVSplat's post-norm U-Net (``ldm_unet/unet.py``, class ``UNetModel``) without timestep
embedding, with cross-view self-attention. Module names follow the reference so checkpoints
load strictly: ``input_blocks.N.M``, ``middle_block.{0,1,2}``, ``output_blocks.N.M``, ``out``.
"""

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn


def group_norm(channels: int) -> nn.GroupNorm:
    """8 groups (4 where the channel count is not divisible by 8), as the reference."""
    return nn.GroupNorm(8 if channels % 8 == 0 else 4, channels)


class ResBlock(nn.Module):
    """conv -> GN -> SiLU -> conv -> GN (zero-init) -> SiLU, plus a 1x1 skip where channels
    change."""

    def __init__(self, channels: int, out_channels: int):
        super().__init__()
        self.in_layers = nn.Sequential(nn.Conv2d(channels, out_channels, 3, padding=1),
                                       group_norm(out_channels), nn.SiLU())
        self.out_layers = nn.Sequential(nn.Conv2d(out_channels, out_channels, 3, padding=1),
                                        group_norm(out_channels), nn.SiLU())
        nn.init.zeros_(self.out_layers[1].weight)
        self.skip_connection = (nn.Identity() if channels == out_channels
                                else nn.Conv2d(channels, out_channels, 1))

    def forward(self, x: Tensor) -> Tensor:
        return self.skip_connection(x) + self.out_layers(self.in_layers(x))


class Downsample(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.op = nn.Conv2d(channels, channels, 3, stride=2, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        return self.op(x)


class Upsample(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv(F.interpolate(x, scale_factor=2, mode="nearest"))


class AttentionBlock(nn.Module):
    """Cross-view self-attention: the tokens of all V views of a scene attend to each other.
    Post-norm: x + GN(proj_out(attention(qkv(x)))), GN per view and zero-initialised. Heads
    split the qkv channels as the reference's legacy order ([head][q, k, v][channel])."""

    def __init__(self, channels: int, head_channels: int, num_views: int):
        super().__init__()
        self.heads = max(channels // head_channels, 1)
        self.num_views = num_views
        self.qkv = nn.Conv1d(channels, 3 * channels, 1)
        self.proj_out = nn.Conv1d(channels, channels, 1)
        self.norm = group_norm(channels)
        nn.init.zeros_(self.norm.weight)

    def forward(self, x: Tensor) -> Tensor:
        vb, c, h, w = x.shape
        v = self.num_views
        b = vb // v
        # "(v b) c h w -> b c (v h w)": every view attends to all views.
        tokens = x.view(v, b, c, h * w).permute(1, 2, 0, 3).reshape(b, c, v * h * w)
        qkv = self.qkv(tokens).view(b, self.heads, 3 * c // self.heads, v * h * w)
        # softmax(q^T k / sqrt(ch)) v per head, fused; [B, heads, T, ch] layout.
        q, k, vals = (t.transpose(-1, -2) for t in qkv.chunk(3, dim=2))
        out = F.scaled_dot_product_attention(q, k, vals)  # [B, heads, T, ch]
        out = out.transpose(-1, -2).reshape(b, c, v, h * w)
        # Back to "(v b) c (h w)" before proj_out and GroupNorm: the norm is per view.
        out = out.permute(2, 0, 1, 3).reshape(vb, c, h * w)
        out = self.norm(self.proj_out(out))
        return x + out.view(vb, c, h, w)


class UNet(nn.Module):
    """Post-norm U-Net: ``len(channel_mult)`` levels, ``num_res_blocks`` ResBlocks per level,
    strided-conv down, nearest+conv up, attention at the downsampling factors in
    ``attention_resolutions``; middle block ResBlock, Identity, ResBlock; out conv+GN+SiLU."""

    def __init__(self, channels: int, channel_mult: tuple[int, ...],
                 attention_resolutions: tuple[int, ...], num_views: int,
                 head_channels: int = 32, num_res_blocks: int = 1):
        super().__init__()
        self.num_views = num_views
        self.input_blocks = nn.ModuleList([nn.Sequential(nn.Conv2d(channels, channels, 3,
                                                                   padding=1))])
        skip_channels = [channels]
        ch, ds = channels, 1
        for level, mult in enumerate(channel_mult):
            for _ in range(num_res_blocks):
                layers: list[nn.Module] = [ResBlock(ch, mult * channels)]
                ch = mult * channels
                if ds in attention_resolutions:
                    layers.append(AttentionBlock(ch, head_channels, num_views))
                self.input_blocks.append(nn.Sequential(*layers))
                skip_channels.append(ch)
            if level != len(channel_mult) - 1:
                self.input_blocks.append(nn.Sequential(Downsample(ch)))
                skip_channels.append(ch)
                ds *= 2
        self.middle_block = nn.Sequential(ResBlock(ch, ch), nn.Identity(), ResBlock(ch, ch))
        self.output_blocks = nn.ModuleList()
        for level, mult in list(enumerate(channel_mult))[::-1]:
            for i in range(num_res_blocks + 1):
                layers = [ResBlock(ch + skip_channels.pop(), mult * channels)]
                ch = mult * channels
                if ds in attention_resolutions:
                    layers.append(AttentionBlock(ch, head_channels, num_views))
                if level and i == num_res_blocks:
                    layers.append(Upsample(ch))
                    ds //= 2
                self.output_blocks.append(nn.Sequential(*layers))
        self.out = nn.Sequential(nn.Conv2d(ch, channels, 3, padding=1), group_norm(channels),
                                 nn.SiLU())

    def set_num_views(self, v: int) -> None:
        for m in self.modules():
            if isinstance(m, AttentionBlock):
                m.num_views = v

    def forward(self, x: Float[Tensor, "vb c h w"]) -> Float[Tensor, "vb c h w"]:
        hs = []
        for block in self.input_blocks:
            x = block(x)
            hs.append(x)
        x = self.middle_block(x)
        for block in self.output_blocks:
            x = block(torch.cat([x, hs.pop()], dim=1))
        return self.out(x)
