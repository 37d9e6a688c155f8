"""MVSplat's Gaussian adapter: raw head outputs + depths -> world-space Gaussians
(``src/model/encoder/common/gaussian_adapter.py``, ``encoder_costvolume.py``).

Kept on purpose, to reproduce official checkpoints: the predicted depth is a distance along the
unit-length ray (pixelSplat's convention), not camera z; scales are in pixel footprints at that
distance; the SH mask damps degree l by 0.1 * 0.25^l.
"""

import torch
from jaxtyping import Float
from torch import Tensor, nn

from usplat_dr.geometry.cameras import pixel_centres
from usplat_dr.geometry.quaternions import quat_xyzw_to_matrix
from usplat_dr.model.sh_rotation import sh_rotation_matrix
from usplat_dr.model.types import Gaussians


def sh_mask(d_sh: int, active_degree: int | None = None) -> Tensor:
    """1 for degree 0, 0.1 * 0.25^l for degree l (MVSplat's ``sh_mask``); 0 above
    ``active_degree`` (None: every degree)."""
    mask = torch.ones(d_sh)
    degree = int(d_sh**0.5) - 1
    for deg in range(1, degree + 1):
        on = active_degree is None or deg <= active_degree
        mask[deg * deg:(deg + 1) ** 2] = 0.1 * 0.25**deg if on else 0.0
    return mask


class GaussianAdapter(nn.Module):
    """``colour_sh_degree``: the degree the colours use (``PrimaryNetworkCfg``); the head's
    coefficients above it are masked to zero."""

    def __init__(self, sh_degree: int = 4, scale_min: float = 0.5, scale_max: float = 15.0,
                 colour_sh_degree: int | None = None):
        super().__init__()
        self.sh_degree = sh_degree
        self.d_sh = (sh_degree + 1) ** 2
        self.scale_min, self.scale_max = scale_min, scale_max
        self.register_buffer("sh_mask", sh_mask(self.d_sh, colour_sh_degree), persistent=False)

    def forward(self, extrinsics: Float[Tensor, "b v 4 4"], intrinsics: Float[Tensor, "b v 3 3"],
                raw: Float[Tensor, "b v r c"], depths: Float[Tensor, "b v r 1 g"],
                opacities: Float[Tensor, "b v r 1 g"], image_shape: tuple[int, int]
                ) -> tuple[Gaussians, Tensor]:
        """Gaussians, and the normalised image coordinates of their centres [B, V, R, 2].

        ``raw`` channels: 0:2 xy-offset logits, 2:5 scale logits, 5:9 xyzw quaternion, then
        3 * d_sh SH coefficients colour-major."""
        h, w = image_shape
        b, v, r, _ = raw.shape
        gpp = depths.shape[-1]
        pixel = torch.tensor([1.0 / w, 1.0 / h], dtype=torch.float32, device=raw.device)
        xy = pixel_centres(h, w, raw.device) + (raw[..., :2].sigmoid() - 0.5) * pixel  # [B,V,R,2]
        scales_raw, quats, sh = raw[..., 2:].split((3, 4, 3 * self.d_sh), dim=-1)
        scales = self.scale_min + (self.scale_max - self.scale_min) * scales_raw.sigmoid()
        kinv = intrinsics[..., :2, :2].inverse()
        multiplier = (0.1 * torch.einsum("...ij,j->...i", kinv, pixel)).sum(-1)  # [B, V]
        d = depths.squeeze(3)  # [B, V, R, G]
        scales = scales[..., None, :] * d[..., None] * multiplier[:, :, None, None, None]
        rotations = quats / (quats.norm(dim=-1, keepdim=True) + 1e-8)  # [B, V, R, 4]

        # Covariance C R S S^T R^T C^T (C: camera-to-world rotation) = sum_k s_k^2 a_k a_k^T
        # with a_k the k-th column of C R: one C R per pixel (shared by its Gaussians), then
        # (A diag(s^2)) A^T as one batched 3x3 product (with torch 2.13 on our CPUs faster
        # than the elementwise product and sum over k it replaced, and equal to it bit for
        # bit: the 256x256 forward's covariances did not change).
        rq = quat_xyzw_to_matrix(rotations)  # [B, V, R, 3, 3]
        axes = torch.einsum("bvij,bvrjk->bvrik", extrinsics[..., :3, :3], rq)[:, :, :, None]
        rotations = rotations[..., None, :].expand(b, v, r, gpp, 4)
        scaled = axes * scales.square()[..., None, :]  # [B, V, R, G, 3, 3]: a_k s_k^2
        cov = scaled @ axes.transpose(-1, -2)

        # Means along the unit ray through the (offset) pixel.
        homo = torch.cat([xy, torch.ones_like(xy[..., :1])], dim=-1)
        dirs = torch.einsum("bvij,bvrj->bvri", intrinsics.inverse(), homo)
        dirs = dirs / dirs.norm(dim=-1, keepdim=True)
        dirs = torch.cat([dirs, torch.zeros_like(dirs[..., :1])], dim=-1)
        dirs = torch.einsum("bvij,bvrj->bvri", extrinsics, dirs)[..., :3]
        origins = extrinsics[..., :3, 3][:, :, None, None]
        means = origins + dirs[:, :, :, None] * d[..., None]  # [B, V, R, G, 3]

        # SH masked (``sh_mask``), then rotated camera -> world by one Wigner-D per view,
        # shared by its Gaussians: both folded into one matrix per view, block-diagonal over
        # the three colours, applied by one batched product that reads the head's output where
        # it lies (BLAS takes its strided rows as they are). The mask is constant per degree
        # and D block-diagonal by degree, so masking before or after rotating is the same up
        # to float rounding. The zeros of the [3 d_sh, 3 d_sh] product cost less than the
        # mask, the copy and the [d_sh, d_sh] products it replaced (at (c)'s 64x64 shapes 2.7
        # -> 0.5 ms; 256x256 at degree 4, 40 -> 25 ms).
        n = self.d_sh
        rot = sh_rotation_matrix(extrinsics[..., :3, :3], self.sh_degree) * self.sh_mask
        per_colour = rot.new_zeros(b, v, 3 * n, 3 * n)
        for c in range(3):  # rows: input coefficient j, columns: output i (D_ij mask_j)
            per_colour[..., c * n:(c + 1) * n, c * n:(c + 1) * n] = rot.transpose(-1, -2)
        harmonics = torch.bmm(sh.flatten(0, 1), per_colour.flatten(0, 1)).view(b, v, r, 3, n)
        harmonics = harmonics[:, :, :, None].expand(b, v, r, gpp, 3, n)

        def flat(t):  # "b v r g ... -> b (v r g) ..."
            return t.reshape(b, v * r * gpp, *t.shape[4:])

        return Gaussians(means=flat(means), covariances=flat(cov), harmonics=flat(harmonics),
                         opacities=opacities.reshape(b, v * r * gpp), scales=flat(scales),
                         rotations=flat(rotations)), xy
