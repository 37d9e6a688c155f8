"""MVSplat's ``DepthPredictorMultiView``: cost-volume refinement, coarse depth, feature
upsampling, depth refinement and the depth/opacity and Gaussian heads. Works in (v b) order, as
the reference ("IMPORTANT: this model is in (v b)").
"""

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from usplat_dr.model.encoder.cost_volume import disparity_candidates, plane_sweep_correlation
from usplat_dr.model.encoder.unet import UNet


@dataclass
class DepthOutputs:
    """What the depth predictor computes, (v b) order unless noted. ``depths`` and ``densities``
    [B, V, H*W, 1, gpp]; ``raw_gaussians`` [B, V, H*W, C] (all three None when the heads were
    not run); ``head_input`` (the Gaussian head's input, channels-last) and ``disp_full``
    (coarse disparity at full resolution) are what the heads need; the rest are intermediates
    kept for tests and visualisation."""

    depths: Tensor | None
    densities: Tensor | None
    raw_gaussians: Tensor | None
    cost_volume: Tensor
    pdf: Tensor
    coarse_disparity: Tensor
    pdf_max: Tensor
    disparity_candidates: Tensor
    raw_to_disparity: Tensor | None
    # The next three are None after ``drop_intermediates``.
    features_fullres: Tensor | None  # upsampled features before proj_feature [VB, C, H, W]
    refine_out: Tensor | None  # input of the heads [VB, 32, H, W]
    head_input: Tensor | None  # input of to_gaussians [VB, 32 + 3 + C, H, W], channels-last
    disp_full: Tensor  # [VB, 1, H, W]

    def drop_intermediates(self) -> None:
        """Release the full-resolution intermediates the Gaussian adapter does not read
        (head input, features, refinement output: ~160 MiB at 2x256x256)."""
        self.head_input = self.features_fullres = self.refine_out = None


def cat_channels_last(parts: tuple[Tensor, ...]) -> Tensor:
    """``torch.cat(parts, 1).contiguous(memory_format=torch.channels_last)`` without the
    channels-first concatenation: the parts are copied into a channels-last tensor."""
    n, _, h, w = parts[0].shape
    dtype = parts[0].dtype
    for p in parts[1:]:  # torch.cat's type promotion
        dtype = torch.promote_types(dtype, p.dtype)
    out = torch.empty((n, sum(p.shape[1] for p in parts), h, w), dtype=dtype,
                      device=parts[0].device, memory_format=torch.channels_last)
    c0 = 0
    for p in parts:
        out[:, c0:c0 + p.shape[1]] = p
        c0 += p.shape[1]
    return out


def lean_sequential(seq: nn.Sequential, x: Tensor) -> Tensor:
    """``seq(x)`` for use without autograd, with each GELU after the first layer applied in
    place on its input (an intermediate of this call): the same numbers, one full-size
    activation fewer at a time."""
    for i, layer in enumerate(seq):
        if i and type(layer) is nn.GELU:
            x = torch.ops.aten.gelu_(x, approximate=layer.approximate)
        else:
            x = layer(x)
    return x


def lean_head(seq: nn.Sequential, x: Tensor) -> Tensor:
    """``seq(x)`` for use without autograd, one batch entry at a time through
    ``lean_sequential``, into a channels-last output like the batched call's: a head's
    hidden layer (168 channels at full resolution for ``to_gaussians``, 84 MiB per view at
    256x256) is the largest activation of the network. The output has the memory format
    of the entries' outputs (channels-last for a channels-last input)."""
    if x.shape[0] == 1:
        return lean_sequential(seq, x)
    out = None
    for i in range(x.shape[0]):
        y = lean_sequential(seq, x[i:i + 1])
        if out is None:
            fmt = (torch.contiguous_format if y.is_contiguous() else torch.channels_last)
            out = torch.empty((x.shape[0], *y.shape[1:]), dtype=y.dtype, device=y.device,
                              memory_format=fmt)
        out[i:i + 1] = y
        del y
    return out


class DepthPredictorMultiView(nn.Module):
    def __init__(self, cfg, num_views: int = 2):
        super().__init__()
        c = cfg.d_feature
        d = cfg.num_depth_candidates
        gpp = cfg.gaussians_per_pixel
        self.cfg = cfg
        unet_c = cfg.costvolume_unet_feat_dim
        if cfg.use_cost_volume_refine:
            self.corr_refine_net = nn.Sequential(
                nn.Conv2d(d + c, unet_c, 3, padding=1), nn.GroupNorm(8, unet_c), nn.GELU(),
                UNet(unet_c, tuple(cfg.costvolume_unet_channel_mult),
                     tuple(cfg.costvolume_unet_attn_res), num_views),
                nn.Conv2d(unet_c, d, 3, padding=1))
        self.regressor_residual = nn.Conv2d(d + c, d, 1)
        self.depth_head_lowres = nn.Sequential(nn.Conv2d(d, 2 * d, 3, padding=1), nn.GELU(),
                                               nn.Conv2d(2 * d, d, 3, padding=1))
        up = cfg.downscale_factor
        self.upsampler = nn.Sequential(
            nn.Conv2d(2 * c, c, 3, padding=1),
            nn.Upsample(scale_factor=up, mode="bilinear", align_corners=True), nn.GELU())
        r = cfg.depth_unet_feat_dim
        self.proj_feature = nn.Conv2d(c, r, 3, padding=1)
        if cfg.use_depth_refine:
            self.refine_unet = nn.Sequential(
                nn.Conv2d(3 + r + 2, r, 3, padding=1), nn.GroupNorm(4, r), nn.GELU(),
                UNet(r, tuple(cfg.depth_unet_channel_mult), tuple(cfg.depth_unet_attn_res),
                     num_views))
        d_sh = (cfg.sh_degree + 1) ** 2
        raw_channels = 7 + 3 * d_sh + 2
        head_in = r + 3 + c
        self.to_gaussians = nn.Sequential(
            nn.Conv2d(head_in, 2 * raw_channels, 3, padding=1), nn.GELU(),
            nn.Conv2d(2 * raw_channels, raw_channels, 3, padding=1))
        self.to_disparity = nn.Sequential(nn.Conv2d(r, 2 * r, 3, padding=1), nn.GELU(),
                                          nn.Conv2d(2 * r, 2 * gpp, 3, padding=1))

    def set_num_views(self, v: int) -> None:
        for m in self.modules():
            if isinstance(m, UNet):
                m.set_num_views(v)

    def forward(self, trans_features: Float[Tensor, "b v c h w"],
                cnn_features: Float[Tensor, "b v c h w"],
                images: Float[Tensor, "b v 3 H W"], extrinsics: Float[Tensor, "b v 4 4"],
                intrinsics: Float[Tensor, "b v 3 3"], near: Float[Tensor, "b v"],
                far: Float[Tensor, "b v"], run_heads: bool = True) -> DepthOutputs:
        cfg = self.cfg
        b, v, c, h, w = trans_features.shape
        self.set_num_views(v)
        feat = trans_features.transpose(0, 1).reshape(v * b, c, h, w)
        cnn = cnn_features.transpose(0, 1).reshape(v * b, c, h, w)
        rgb = images.transpose(0, 1).flatten(0, 1)  # [(v b), 3, H, W]
        disps = disparity_candidates(near, far, cfg.num_depth_candidates).type_as(feat)

        # ---- Cost volume and its refinement ----
        if cfg.use_cost_volume:
            cost = plane_sweep_correlation(trans_features, extrinsics, intrinsics, disps,
                                           cfg.cost_volume_method, cfg.cost_volume_chunk)
        else:  # ablation: no matching information, only the features
            cost = feat.new_zeros(v * b, cfg.num_depth_candidates, h, w)
        cost_in = torch.cat((cost, feat), dim=1)
        refined = self.regressor_residual(cost_in)
        if cfg.use_cost_volume_refine:
            refined = self.corr_refine_net(cost_in) + refined

        # ---- Coarse depth ----
        pdf = F.softmax(self.depth_head_lowres(refined), dim=1)
        d4 = disps[:, :, None, None]
        coarse = (d4 * pdf).sum(dim=1, keepdim=True)
        pdf_max = torch.max(pdf, dim=1, keepdim=True)[0]
        up = cfg.downscale_factor
        pdf_max_full = F.interpolate(pdf_max, scale_factor=up)
        disp_full = F.interpolate(coarse, scale_factor=up, mode="bilinear", align_corners=True)

        # ---- Depth refinement ----
        # Without autograd ("lean"), full-resolution tensors are released as soon as they
        # are used, and the upsampled features are computed again for the heads (a bilinear
        # upsampling and a GELU, ~1% of the forward) instead of being kept through the
        # refinement U-Net: at 2x256x256, 64 MiB less at the peak. Same numbers either way.
        # (The lean path runs the upsampler's layers one by one: hooks on the upsampler
        # itself fire only with autograd, hooks on its layers always.)
        lean = not torch.is_grad_enabled()
        if lean:
            low = self.upsampler[0](torch.cat((feat, cnn), dim=1))

            def upsampled():  # the upsampler's remaining layers (Upsample, GELU)
                return lean_sequential(self.upsampler[1:], low)

            refine_out = self.proj_feature(upsampled())
            features_full = None
        else:
            features_full = self.upsampler(torch.cat((feat, cnn), dim=1))
            refine_out = self.proj_feature(features_full)
        if cfg.use_depth_refine:  # (else, the ablation: the heads see the projection)
            refine_out = self.refine_unet(
                torch.cat((rgb, refine_out, disp_full, pdf_max_full), 1))
        if features_full is None:
            features_full = upsampled()

        # ---- Heads ----
        # channels_last: ~25% faster convolutions on CPU here, and it is the [.., H*W, C]
        # layout the Gaussian adapter reads anyway.
        parts = (refine_out, rgb, features_full)
        if lean:  # written in place: no channels-first concatenation beside it
            head_input = cat_channels_last(parts)
        else:  # (one expression: the channels-first concatenation is freed at once)
            head_input = torch.cat(parts, dim=1).contiguous(memory_format=torch.channels_last)
        del parts
        # The full-resolution features live on as a view of the head input.
        features_full = head_input[:, refine_out.shape[1] + rgb.shape[1]:]
        out = DepthOutputs(
            depths=None, densities=None, raw_gaussians=None, cost_volume=cost, pdf=pdf,
            coarse_disparity=coarse, pdf_max=pdf_max, disparity_candidates=disps,
            raw_to_disparity=None, features_fullres=features_full, refine_out=refine_out,
            head_input=head_input, disp_full=disp_full)
        if not run_heads:
            return out
        # (without autograd through ``lean_head``: one view at a time, GELUs in place)
        run = lean_head if lean else nn.Sequential.__call__
        out.raw_gaussians = self.gaussians_layout(run(self.to_gaussians, head_input), v, b)
        out.raw_to_disparity = run(self.to_disparity, refine_out)
        out.depths, out.densities = self.depths_from(out.raw_to_disparity, disp_full, near, far)
        return out

    @staticmethod
    def gaussians_layout(raw: Tensor, v: int, b: int) -> Tensor:
        """Gaussian-head output [(v b), C, H, W] -> [B, V, H*W, C]."""
        big_h, big_w = raw.shape[-2:]
        return raw.view(v, b, -1, big_h * big_w).permute(1, 0, 3, 2)

    def depths_from(self, raw_disp: Float[Tensor, "vb c h w"],
                    disp_full: Float[Tensor, "vb 1 h w"], near: Float[Tensor, "b v"],
                    far: Float[Tensor, "b v"]) -> tuple[Tensor, Tensor]:
        """Depths and densities [B, V, H*W, 1, gpp] from the depth head's output and the coarse
        disparity, both in (v b) order."""
        gpp = self.cfg.gaussians_per_pixel
        b, v = near.shape
        big_h, big_w = raw_disp.shape[-2:]
        delta, logits = raw_disp.split(gpp, dim=1)
        lo = (1.0 / far).t().reshape(-1, 1, 1, 1)
        hi = (1.0 / near).t().reshape(-1, 1, 1, 1)
        depths = 1.0 / (disp_full + delta).clamp(lo, hi)

        def bv(t):  # "(v b) dpt h w -> b v (h w) srf dpt"
            return t.view(v, b, gpp, big_h * big_w).permute(1, 0, 3, 2).unsqueeze(3)

        return bv(depths), bv(torch.sigmoid(logits))
