"""UniqueSplat's view-specific branch up to the embedding: E_H (ResNet18) on the context
images, Proj into each target view, phi -> e_s.

Our reading where the UniqueSplat paper (Song et al.) is vague:
- F_c: the ResNet18 stages' outputs, each mapped to ``feature_dim`` channels by a 1x1 conv and
  resampled to the stride-8 grid (``layer2``'s), summed (a one-level feature pyramid: every
  stage used, fine enough for epipolar matching).
- "after fusion with the target view matrix": phi sees, beside F_t, the target rays in the
  first context camera's frame (direction, and origin in units of the context baseline), so
  that the embedding knows where the target is even where correlations say nothing
  (textureless regions).
- phi: 4 blocks of 3x3 stride-2 conv + GroupNorm + GELU, global average pooling, a linear layer
  to ``embed_dim``.
"""

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from usplat_dr.model.hypernet.epipolar import EpipolarProjection, target_rays
from usplat_dr.model.hypernet.resnet import ResNet18


class ContextFeatures(nn.Module):
    """E_H and the lateral convs: images [B, V, 3, H, W] -> F_c [B, V, C, H/8, W/8].

    The ResNet's BatchNorm layers always use their running statistics (frozen BatchNorm, as
    detection and pixelSplat-style backbones fine-tune pretrained ResNets; their affine
    parameters still train): with 1-2 scenes per GPU, batch statistics would be noise, and a
    scene's features would depend on the other scenes in its batch and on how the batch is
    split between ranks."""

    def __init__(self, stages: int = 4, feature_dim: int = 64):
        super().__init__()
        self.resnet = ResNet18(num_classes=None, stages=stages)
        self.lateral = nn.ModuleList(nn.Conv2d(c, feature_dim, 1) for c in self.resnet.channels)

    def train(self, mode: bool = True) -> "ContextFeatures":
        super().train(mode)
        for m in self.resnet.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.eval()
        return self

    def forward(self, images: Float[Tensor, "b v 3 h w"]) -> Float[Tensor, "b v c h8 w8"]:
        b, v, _, h, w = images.shape
        size = (h // 8, w // 8)
        fused = 0
        for lateral, f in zip(self.lateral, self.resnet.features(images.flatten(0, 1))):
            y = lateral(f)
            if y.shape[-2:] != size:
                # float32: torch has no bfloat16 antialiased resize (bfloat16 inference)
                y = F.interpolate(y.float(), size=size, mode="bilinear", align_corners=False,
                                  antialias=y.shape[-1] > size[1])
            fused = fused + y
        return fused.unflatten(0, (b, v))


class PrimaryFeatures(nn.Module):
    """E_H as a reader of the primary network: its backbone's full-resolution features (the
    depth predictor's ``features_fullres``: CNN + transformer, trained to match across views),
    area-averaged to the stride-8 grid and mapped to ``feature_dim`` channels by a 1x1 conv.
    Detached: the branch reads the encoder and never trains it."""

    def __init__(self, in_channels: int, feature_dim: int = 64):
        super().__init__()
        self.lateral = nn.Conv2d(in_channels, feature_dim, 1)

    def forward(self, features: Float[Tensor, "b v c h w"]) -> Float[Tensor, "b v f h8 w8"]:
        b, v, _, h, w = features.shape
        x = F.adaptive_avg_pool2d(features.detach().flatten(0, 1).float(),
                                  (max(h // 8, 1), max(w // 8, 1)))
        return self.lateral(x).unflatten(0, (b, v))


def camera_channels(extrinsics: Float[Tensor, "b v 4 4"], intrinsics: Float[Tensor, "b v 3 3"],
                    target_extrinsics: Float[Tensor, "b n 4 4"],
                    target_intrinsics: Float[Tensor, "b n 3 3"], grid: tuple[int, int]
                    ) -> Float[Tensor, "b n 6 gh gw"]:
    """Target rays in the first context camera's frame: unit direction, and tanh of the origin
    divided by the mean distance between the context cameras (over all pairs: the distance of
    the two for V = 2; scale-free, and bounded when the context cameras coincide)."""
    origins, dirs = target_rays(target_extrinsics, target_intrinsics, grid)  # world
    w2c = extrinsics[:, :1].inverse()  # [B, 1, 4, 4]
    rot, trans = w2c[..., :3, :3], w2c[..., :3, 3]
    d = F.normalize(torch.einsum("bnij,bnpj->bnpi", rot, dirs), dim=-1)
    o = torch.einsum("bnij,bnpj->bnpi", rot, origins) + trans[:, :, None]
    centres = extrinsics[:, :, :3, 3]
    pairs = torch.triu_indices(centres.shape[1], centres.shape[1], 1, device=centres.device)
    baseline = (centres[:, pairs[0]] - centres[:, pairs[1]]).norm(dim=-1).mean(-1)
    o = torch.tanh(o / baseline.clamp(min=1e-6)[:, None, None, None])
    rays = torch.cat((d, o.expand_as(d)), -1)  # [B, N, P, 6]
    return rays.transpose(-1, -2).unflatten(-1, grid)


class Phi(nn.Module):
    """4 conv blocks + a linear layer: F_t [T, C, gh, gw] -> e_s [T, embed_dim]."""

    def __init__(self, in_channels: int, channels: tuple[int, ...], embed_dim: int):
        super().__init__()
        if len(channels) != 4:
            raise ValueError(f"phi has 4 conv blocks: phi_channels needs 4 widths, got "
                             f"{channels}")
        blocks, c = [], in_channels
        for c_out in channels:
            blocks += [nn.Conv2d(c, c_out, 3, stride=2, padding=1), nn.GroupNorm(8, c_out),
                       nn.GELU()]
            c = c_out
        self.blocks = nn.Sequential(*blocks)
        self.linear = nn.Linear(c, embed_dim)

    def forward(self, x: Float[Tensor, "t c gh gw"]) -> Float[Tensor, "t d"]:
        return self.linear(self.blocks(x).mean((-2, -1)))


class ViewSpecificEmbedding(nn.Module):
    """Context images and cameras, target cameras -> e_s [B, N, embed_dim] (and Proj's aux)."""

    def __init__(self, resnet_stages: int, feature_dim: int, num_samples: int,
                 temperature: float, proj_stride: int, phi_channels: tuple[int, ...],
                 embed_dim: int, primary_channels: int | None = None):
        super().__init__()
        self.proj_stride = proj_stride
        # E_H: a ResNet18 on the images (the paper), or the primary network's features
        # (``primary_channels``, their channel count; ``forward``'s ``context_features``)
        self.features = (ContextFeatures(resnet_stages, feature_dim) if primary_channels is None
                         else PrimaryFeatures(primary_channels, feature_dim))
        self.proj = EpipolarProjection(num_samples, temperature)
        self.phi = Phi(feature_dim + 6, phi_channels, embed_dim)

    def forward(self, images: Float[Tensor, "b v 3 h w"], extrinsics: Float[Tensor, "b v 4 4"],
                intrinsics: Float[Tensor, "b v 3 3"], target_extrinsics: Float[Tensor, "b n 4 4"],
                target_intrinsics: Float[Tensor, "b n 3 3"], target_near: Float[Tensor, "b n"],
                target_far: Float[Tensor, "b n"], context_features: Tensor | None = None
                ) -> tuple[Tensor, dict]:
        h, w = images.shape[-2:]
        grid = (max(h // self.proj_stride, 1), max(w // self.proj_stride, 1))
        if isinstance(self.features, PrimaryFeatures):
            if context_features is None:
                raise ValueError("context_features: this E_H reads the primary network's "
                                 "features [B, V, C, H, W]; pass them")
            f_c = self.features(context_features)
        else:
            f_c = self.features(images)
        f_t, aux = self.proj(f_c, extrinsics, intrinsics, target_extrinsics, target_intrinsics,
                             target_near, target_far, grid)
        cams = camera_channels(extrinsics, intrinsics, target_extrinsics, target_intrinsics,
                               grid)
        x = torch.cat((f_t, cams), 2).flatten(0, 1)  # [B N, C + 6, gh, gw]
        return self.phi(x).unflatten(0, f_t.shape[:2]), aux
