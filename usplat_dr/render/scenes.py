"""Procedural Gaussian scenes (torch) for tests, benchmarks and the render demo.

``pixel_aligned_scene`` is the realistic-overlap scene (docs/rasteriser_notes.md, "Tiles,
records and the benchmark scene"): one Gaussian per pixel of two nearby context views,
unprojected at random depths (what a feed-forward model such as MVSplat predicts), rendered from
a third camera between them.
"""

import math
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from usplat_dr.geometry.cameras import look_at, normalized_intrinsics
from usplat_dr.geometry.quaternions import quat_xyzw_to_matrix
from usplat_dr.render.sh import C0


@dataclass
class GaussianScene:
    """Render arguments for ``usplat_dr.render.rasterize`` (batch of B cameras, G Gaussians)."""

    extrinsics: Float[Tensor, "batch 4 4"]
    intrinsics: Float[Tensor, "batch 3 3"]
    near: Float[Tensor, " batch"]
    far: Float[Tensor, " batch"]
    image_shape: tuple[int, int]
    background_color: Float[Tensor, "batch 3"]
    means: Float[Tensor, "batch gaussian 3"]
    covariances: Float[Tensor, "batch gaussian 3 3"]
    sh_coefficients: Float[Tensor, "batch gaussian 3 d_sh"]
    opacities: Float[Tensor, "batch gaussian"]

    def args(self) -> tuple:
        """Positional arguments of ``rasterize``."""
        return (self.extrinsics, self.intrinsics, self.near, self.far, self.image_shape,
                self.background_color, self.means, self.covariances, self.sh_coefficients,
                self.opacities)

    def to(self, device=None, dtype=None) -> "GaussianScene":
        def cv(t):
            return t.detach().to(device=device, dtype=dtype)

        return GaussianScene(cv(self.extrinsics), cv(self.intrinsics), cv(self.near),
                             cv(self.far), self.image_shape, cv(self.background_color),
                             cv(self.means), cv(self.covariances), cv(self.sh_coefficients),
                             cv(self.opacities))


def random_rotations(n: int, generator: torch.Generator) -> Float[Tensor, "n 3 3"]:
    """Uniformly random rotation matrices (from normalised Gaussian quaternions)."""
    q_wxyz = torch.randn(n, 4, generator=generator)
    return quat_xyzw_to_matrix(q_wxyz[:, [1, 2, 3, 0]])


def covariances_from(rotations: Tensor, scales: Tensor) -> Tensor:
    """R diag(s)^2 R^T."""
    return rotations @ torch.diag_embed(scales * scales) @ rotations.transpose(-1, -2)


def sh_from_rgb(rgb: Tensor, degree: int, generator: torch.Generator,
                view_dependence: float = 0.0) -> Tensor:
    """[G, 3, (degree+1)^2] coefficients whose DC term gives ``rgb``; higher bands random with
    standard deviation ``view_dependence``."""
    d = (degree + 1) ** 2
    sh = view_dependence * torch.randn(rgb.shape[0], 3, d, generator=generator)
    sh[..., 0] = (rgb - 0.5) / C0
    return sh


def orbit_cameras(num: int, radius: float, height: float, arc_degrees: float = 360.0,
                  target=(0.0, 0.0, 0.0)) -> Float[Tensor, "num 4 4"]:
    """OpenCV c2w cameras on a horizontal circle (world up = -Y) looking at ``target``."""
    angles = torch.linspace(0, math.radians(arc_degrees), num + (arc_degrees >= 360.0))[:num]
    eye = torch.stack([radius * torch.sin(angles), torch.full_like(angles, -height),
                       -radius * torch.cos(angles)], -1)
    tgt = torch.tensor(target).expand(num, 3)
    up = torch.tensor([0.0, -1.0, 0.0]).expand(num, 3)
    return look_at(eye, tgt, up)


def isotropic_scene(num_gaussians: int, size: int = 256, sh_degree: int = 0,
                    seed: int = 0) -> GaussianScene:
    """Random isotropic Gaussians in front of a camera at the origin looking down +z: a scene
    unlike the pixel-aligned one (few pixels per Gaussian, one view), as a user writes one.
    Centres ``normal(0, 1) * (1, 1, 0.6) + (0, 0, 4)``, covariance 0.0009 I, opacity 0.6,
    random SH coefficients; focal 1 (normalised), near 0.5, far 100, ``size`` x ``size``.

    Examples:
        >>> s = isotropic_scene(100, size=32)
        >>> s.means.shape, s.image_shape
        (torch.Size([1, 100, 3]), (32, 32))
    """
    gen = torch.Generator().manual_seed(seed)
    n = num_gaussians
    means = torch.randn(n, 3, generator=gen) * torch.tensor([1.0, 1.0, 0.6]) \
        + torch.tensor([0.0, 0.0, 4.0])
    return GaussianScene(
        extrinsics=torch.eye(4)[None], intrinsics=normalized_intrinsics(1.0, 1.0)[None],
        near=torch.tensor([0.5]), far=torch.tensor([100.0]), image_shape=(size, size),
        background_color=torch.zeros(1, 3), means=means[None],
        covariances=(0.0009 * torch.eye(3)).expand(1, n, 3, 3).clone(),
        sh_coefficients=torch.rand(1, n, 3, (sh_degree + 1) ** 2, generator=gen),
        opacities=torch.full((1, n), 0.6))


def pixel_aligned_scene(height: int, width: int, batch: int = 1, seed: int = 0,
                        sh_degree: int = 0, opacity_range=(0.2, 0.9), scale_range=(0.3, 1.2),
                        depth_range=(1.0, 10.0), focal: float = 1.0) -> GaussianScene:
    """2 H W Gaussians unprojected from two views, rendered from a third between them.

    Context cameras at x = -0.1 and +0.1 (baseline 0.2), yawed by +-2 degrees and pitched by
    1 degree; each pixel gets one Gaussian at a uniform random depth, anisotropic with random
    rotation and per-axis scale ``scale_range`` x its pixel footprint, opacity uniform in
    ``opacity_range``, random colour. The target camera sits at the origin; with ``batch`` > 1
    each image gets its own scene (seed + b) and a slightly shifted target.
    """
    means, covs, shs, opacs, c2ws = [], [], [], [], []
    K = normalized_intrinsics(focal, focal)
    fx_pix = focal * width
    for b in range(batch):
        gen = torch.Generator().manual_seed(seed + b)
        per_view = []
        for side in (-1.0, 1.0):
            yaw, pitch = math.radians(2.0) * side, math.radians(1.0)
            cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
            ry = torch.tensor([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
            rx = torch.tensor([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
            r = ry @ rx
            origin = torch.tensor([0.1 * side, 0.0, 0.0])
            jj, ii = torch.meshgrid(torch.arange(width), torch.arange(height), indexing="xy")
            x = ((jj + 0.5) / width - K[0, 2]) / K[0, 0]
            y = ((ii + 0.5) / height - K[1, 2]) / K[1, 1]
            rays = torch.stack([x, y, torch.ones_like(x)], -1).reshape(-1, 3)
            depth = torch.empty(rays.shape[0]).uniform_(*depth_range, generator=gen)
            per_view.append((origin + (rays * depth[:, None]) @ r.T, depth))
        pts = torch.cat([p for p, _ in per_view])
        depth = torch.cat([d for _, d in per_view])
        n = pts.shape[0]
        footprint = depth / fx_pix
        scales = footprint[:, None] * torch.empty(n, 3).uniform_(*scale_range, generator=gen)
        covs.append(covariances_from(random_rotations(n, gen), scales))
        means.append(pts)
        rgb = torch.rand(n, 3, generator=gen)
        shs.append(sh_from_rgb(rgb, sh_degree, gen, view_dependence=0.05))
        opacs.append(torch.empty(n).uniform_(*opacity_range, generator=gen))
        c2w = torch.eye(4)
        c2w[0, 3] = 0.01 * b
        c2ws.append(c2w)
    return GaussianScene(
        extrinsics=torch.stack(c2ws), intrinsics=K.expand(batch, 3, 3).clone(),
        near=torch.full((batch,), 0.1), far=torch.full((batch,), 100.0),
        image_shape=(height, width), background_color=torch.zeros(batch, 3),
        means=torch.stack(means), covariances=torch.stack(covs), sh_coefficients=torch.stack(shs),
        opacities=torch.stack(opacs))


def random_scene(num_gaussians: int, height: int, width: int, batch: int = 1, seed: int = 0,
                 sh_degree: int = 1, opacity_range=(0.05, 0.95), scale_range=(0.02, 0.3),
                 background=None) -> GaussianScene:
    """Random Gaussians in a box in front of ``batch`` cameras looking at the origin from
    distance 4 (world up -Y), with random anisotropic covariances and SH colours."""
    gen = torch.Generator().manual_seed(seed)
    n = num_gaussians
    means = (torch.rand(batch, n, 3, generator=gen) - 0.5) * 2.0
    rot = random_rotations(batch * n, gen).reshape(batch, n, 3, 3)
    scales = torch.empty(batch, n, 3).uniform_(*scale_range, generator=gen)
    covs = covariances_from(rot, scales)
    rgb = torch.rand(batch * n, 3, generator=gen)
    sh = sh_from_rgb(rgb, sh_degree, gen, view_dependence=0.3).reshape(batch, n, 3, -1)
    opac = torch.empty(batch, n).uniform_(*opacity_range, generator=gen)
    c2w = orbit_cameras(batch, radius=4.0, height=0.5, arc_degrees=90.0)
    bg = torch.rand(batch, 3, generator=gen) if background is None else background
    return GaussianScene(
        extrinsics=c2w, intrinsics=normalized_intrinsics(1.1, 1.1 * width / height,
                                                         batch=(batch,)),
        near=torch.full((batch,), 0.5), far=torch.full((batch,), 50.0),
        image_shape=(height, width), background_color=bg, means=means, covariances=covs,
        sh_coefficients=sh, opacities=opac)
