"""Proj(F_c, P_c, P_t) of UniqueSplat's view-specific branch: context features gathered along
each target ray's epipolar lines and fused by cross-view cosine correlation.

Our reading of the UniqueSplat paper (Song et al.; the choices are ours): for every pixel of a
reduced target grid, the ray x(z) = o + z r (r = R_t K_t^-1 [u, v, 1], so z is the target
camera's depth) is sampled at ``n`` depths between near and far (uniform in inverse depth, as
MVSplat's candidates: uniform in depth would put almost every sample near ``far`` for RE10K's
1..100). Each sample is projected into every context view (P = K [R | t]) and the context
features are sampled bilinearly there; samples behind a camera or outside its image are
invalid. The cosine similarity of the views' features at a sample (mean over view pairs)
measures photo-consistency; a softmax over the samples of ray (temperature learnable) weights
the views' mean feature into the target feature.
"""

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float
from torch import Tensor, nn

from usplat_dr.geometry.cameras import pixel_centres


def target_rays(extrinsics: Float[Tensor, "b n 4 4"], intrinsics: Float[Tensor, "b n 3 3"],
                grid: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Origins [B, N, 1, 3] and directions [B, N, P, 3] (P = gh * gw pixel centres of a
    ``grid`` over the image, raster order) scaled so that o + z d has camera depth z."""
    xy = pixel_centres(*grid, intrinsics.device, intrinsics.dtype)
    pix = torch.cat([xy, torch.ones_like(xy[:, :1])], -1)  # normalised homogeneous coords
    cam = torch.einsum("bnij,pj->bnpi", intrinsics.inverse(), pix)  # z = 1
    dirs = torch.einsum("bnij,bnpj->bnpi", extrinsics[..., :3, :3], cam)
    return extrinsics[..., None, :3, 3], dirs


def sample_depths(near: Float[Tensor, "b n"], far: Float[Tensor, "b n"], num: int
                  ) -> Float[Tensor, "b n s"]:
    """``num`` depths uniform in inverse depth, far to near."""
    t = torch.linspace(0.0, 1.0, num, device=near.device, dtype=near.dtype)
    disp = 1 / far[..., None] + t * (1 / near[..., None] - 1 / far[..., None])
    return 1 / disp


def project(points: Float[Tensor, "b n p s 3"], extrinsics: Float[Tensor, "b v 4 4"],
            intrinsics: Float[Tensor, "b v 3 3"]) -> tuple[Tensor, Tensor]:
    """Normalised image coordinates [B, N, V, P, S, 2] of world points in each context view,
    and validity [B, N, V, P, S] (in front of the camera and inside the image)."""
    w2c = extrinsics.inverse()
    cam = (torch.einsum("bvij,bnpsj->bnvpsi", w2c[..., :3, :3], points)
           + w2c[:, None, :, None, None, :3, 3])
    z = cam[..., 2:]
    img = torch.einsum("bvij,bnvpsj->bnvpsi", intrinsics, cam / z.clamp(min=1e-6))[..., :2]
    valid = (z[..., 0] > 1e-6) & (img >= 0).all(-1) & (img <= 1).all(-1)
    return img, valid


def cosine_correlation(samples: Float[Tensor, "b n p v s c"], valid: Bool[Tensor, "b n p v s"]
                       ) -> Float[Tensor, "b n p s"]:
    """Mean over context-view pairs of the cosine similarity of their features at each sample
    (0 where either is invalid). cos = <a, b> / sqrt(|a|^2 |b|^2 + eps): one division per
    sample pair, not per channel."""
    sq = samples.square().sum(-1)  # [B, N, P, V, S]
    v = samples.shape[3]
    total, count = 0, 0
    for i in range(v):
        for j in range(i + 1, v):
            both = valid[:, :, :, i] & valid[:, :, :, j]
            dot = (samples[:, :, :, i] * samples[:, :, :, j]).sum(-1)
            cos = dot / (sq[:, :, :, i] * sq[:, :, :, j] + 1e-24).sqrt()
            total = total + cos * both
            count = count + both.float()
    return total / count.clamp(min=1) if v > 1 else torch.zeros_like(valid[:, :, :, 0]).float()


class EpipolarProjection(nn.Module):
    """F_t = Proj(F_c, P_c, P_t) on a ``grid`` target grid with ``num_samples`` per ray."""

    def __init__(self, num_samples: int = 32, temperature: float = 10.0):
        super().__init__()
        self.num_samples = num_samples
        self.log_temperature = nn.Parameter(torch.tensor(float(temperature)).log())

    def forward(self, features: Float[Tensor, "b v c h w"],
                extrinsics: Float[Tensor, "b v 4 4"], intrinsics: Float[Tensor, "b v 3 3"],
                target_extrinsics: Float[Tensor, "b n 4 4"],
                target_intrinsics: Float[Tensor, "b n 3 3"], target_near: Float[Tensor, "b n"],
                target_far: Float[Tensor, "b n"], grid: tuple[int, int]
                ) -> tuple[Tensor, dict]:
        """Target features [B, N, C, gh, gw] on a ``grid`` = (gh, gw) of target pixels, and
        ``aux`` (``correlation`` and ``weights`` [B, N, P, S], ``depths`` [B, N, S])."""
        b, v, c, h, w = features.shape
        n = target_intrinsics.shape[1]
        gh, gw = grid
        origins, dirs = target_rays(target_extrinsics, target_intrinsics, (gh, gw))
        depths = sample_depths(target_near, target_far, self.num_samples)  # [B, N, S]
        points = origins[..., None, :] + dirs[..., None, :] * depths[:, :, None, :, None]
        xy, valid = project(points, extrinsics, intrinsics)  # [B, N, V, P, S, 2]
        p, s = points.shape[2], points.shape[3]
        grid = (2 * xy - 1).permute(0, 2, 1, 3, 4, 5).reshape(b * v, n * p, s, 2)
        sampled = F.grid_sample(features.reshape(b * v, c, h, w), grid, mode="bilinear",
                                padding_mode="zeros", align_corners=False)  # [BV, C, NP, S]
        # [B, N, P, V, S, C] from here on: the reductions below run over contiguous memory,
        # and the fusion is one matrix product per pixel over (view, sample) pairs.
        sampled = sampled.view(b, v, c, n, p, s).permute(0, 3, 4, 1, 5, 2).contiguous()
        valid_p = valid.permute(0, 1, 3, 2, 4)  # [B, N, P, V, S]
        corr = cosine_correlation(sampled, valid_p)  # [B, N, P, S]
        any_valid = valid.any(2)  # [B, N, P, S]
        logits = (self.log_temperature.exp() * corr).masked_fill(~any_valid, -1e4)
        weights = torch.softmax(logits, dim=-1)
        # F_t = sum_s w_s * mean over the views that see sample s of their features
        vmask = valid_p.float()
        coeff = weights[:, :, :, None] * vmask / vmask.sum(3, keepdim=True).clamp(min=1)
        fused = (coeff.reshape(b, n, p, 1, v * s) @ sampled.view(b, n, p, v * s, c))
        fused = fused.view(b, n, p, c)
        aux = {"correlation": corr, "weights": weights, "depths": depths, "valid": valid}
        return fused.transpose(-1, -2).reshape(b, n, c, gh, gw), aux
