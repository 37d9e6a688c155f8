"""Dense reference of the 3DGS CUDA rasteriser in torch, written from the equations: the
oracle the tests compare every stage of the rasteriser with (tests/render/), and the dense
baseline of train/bench/rasterizer.py (like gsplat's ``_torch_impl``).

Every Gaussian against every pixel, in depth order, with the reference's rules (scale-invariant
near cull, EWA with clamped Jacobian and 0.3 dilation, 3-sigma radius, 16x16 tile cut, power > 0
and alpha < 1/255 skips, 0.99 clamp, stop before T < 1e-4). Autograd gives its gradients. It
takes any float dtype (the tests use float64). Independent of the rest of ``usplat_dr.render``:
it imports nothing from usplat_dr and shares no code with the rasteriser. P x G memory (pixels
x Gaussians): small images only.
"""

import math

import torch
from jaxtyping import Float
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
      0.5462742152960396]
C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435]


def sh_basis_3dgs(d: torch.Tensor, degree: int) -> torch.Tensor:
    """[..., (degree+1)^2] standard 3DGS basis (forward.cu ``computeColorFromSH``)."""
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        out += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * z * z - x * x - y * y),
                C2[3] * x * z, C2[4] * (x * x - y * y)]
    if degree >= 3:
        out += [C3[0] * y * (3 * x * x - y * y), C3[1] * x * y * z,
                C3[2] * y * (4 * z * z - x * x - y * y),
                C3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y),
                C3[4] * x * (4 * z * z - x * x - y * y), C3[5] * z * (x * x - y * y),
                C3[6] * x * (x * x - 3 * y * y)]
    return torch.stack(out, -1)


def sh_basis_mvsplat(d: torch.Tensor, degree: int) -> torch.Tensor:
    """[..., (degree+1)^2] basis of diff-gaussian-rasterization-modified, from the table in
    ``docs/mvsplat_notes.md`` sec. 3 (coefficient-14 anomaly included)."""
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * x, C1 * y, -C1 * z]
    if degree >= 2:
        out += [C2[0] * z * x, C2[1] * x * y, C2[2] * (2 * y * y - z * z - x * x),
                C2[3] * z * y, C2[4] * (z * z - x * x)]
    if degree >= 3:
        out += [C3[0] * x * (3 * z * z - x * x), C3[1] * z * x * y,
                C3[2] * x * (4 * y * y - z * z - x * x),
                C3[3] * y * (2 * y * y - 3 * z * z - 3 * x * x),
                C3[4] * z * (4 * y * y - z * z - x * x), C3[5] * z * (z * z - x * x),
                C3[6] * z * (z * z - 3 * x * x)]
    return torch.stack(out, -1)


def project_ref(c2w: Float[Tensor, "4 4"], K: Float[Tensor, "3 3"], near, W, H, means, covs):
    """Per-Gaussian u, v, conic, z, radius, valid for one image (float64)."""
    w2c = torch.linalg.inv(c2w)
    R, t = w2c[:3, :3], w2c[:3, 3]
    fx, fy = K[0, 0] * W, K[1, 1] * H
    cx, cy = K[0, 2] * W, K[1, 2] * H
    p = means @ R.T + t
    x, y, z = p.unbind(-1)
    valid = z > 0.2 * near
    zs = torch.where(valid, z, torch.ones_like(z))
    lim_xp = ((W - cx) + 0.15 * W) / fx
    lim_xn = (cx + 0.15 * W) / fx
    lim_yp = ((H - cy) + 0.15 * H) / fy
    lim_yn = (cy + 0.15 * H) / fy
    txz = torch.clamp(x / zs, -lim_xn, lim_xp)
    tyz = torch.clamp(y / zs, -lim_yn, lim_yp)
    zero = torch.zeros_like(zs)
    J = torch.stack([torch.stack([fx / zs, zero, -fx * txz / zs], -1),
                     torch.stack([zero, fy / zs, -fy * tyz / zs], -1)], -2)  # [G, 2, 3]
    # The reference reads the upper triangle (cov3D_precomp: xx, xy, xz, yy, yz, zz).
    upper = torch.triu(covs)
    sigma = upper + upper.transpose(-1, -2) - torch.diag_embed(torch.diagonal(covs, 0, -2, -1))
    T = J @ R
    blur = 0.3 * torch.eye(2, dtype=covs.dtype, device=covs.device)
    cov2 = T @ sigma @ T.transpose(-1, -2) + blur
    a, b, c = cov2[:, 0, 0], cov2[:, 0, 1], cov2[:, 1, 1]
    det = a * c - b * b
    valid = valid & (det > 0)
    dets = torch.where(valid, det, torch.ones_like(det))
    conic = torch.stack([c / dets, -b / dets, a / dets], -1)
    mid = 0.5 * (a + c)
    lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
    radius = torch.ceil(3 * torch.sqrt(lam.detach().clamp(min=0)))
    u = fx * x / zs + cx
    v = fy * y / zs + cy
    return u, v, conic, z, radius, valid


def render_ref(extrinsics: Float[Tensor, "batch 4 4"], intrinsics: Float[Tensor, "batch 3 3"],
               near, far, image_shape, background, means, covs, sh, opacities,
               tile_cut: bool = True, basis: str = "3dgs", clamp_gradient: str = "exact"):
    """Dense reference render of a batch. Inputs as ``usplat_dr.render.rasterize`` (any float
    dtype; use float64). Returns (color [B,3,H,W], alpha [B,H,W], depth [B,H,W]).

    ``clamp_gradient="reference"`` passes the gradient straight through the 0.99 clamp, as the
    3DGS backward does; ``"exact"`` differentiates the clamp (zero where it is active)."""
    H, W = image_shape
    colors, alphas, depths = [], [], []
    degree = min(math.isqrt(sh.shape[-1]) - 1, 3)
    basis_fn = sh_basis_3dgs if basis == "3dgs" else sh_basis_mvsplat
    grid = {"dtype": means.dtype, "device": means.device}
    jj, ii = torch.meshgrid(torch.arange(W, **grid), torch.arange(H, **grid), indexing="xy")
    pix_x, pix_y = (jj + 0.5).reshape(-1), (ii + 0.5).reshape(-1)  # row-major
    for bi in range(extrinsics.shape[0]):
        u, v, conic, z, radius, valid = project_ref(extrinsics[bi], intrinsics[bi], near[bi], W,
                                                    H, means[bi], covs[bi])
        d = means[bi] - extrinsics[bi, :3, 3]
        d = d / d.norm(dim=-1, keepdim=True)
        nc = (degree + 1) ** 2
        rgb = (sh[bi][..., :nc] * basis_fn(d, degree)[:, None, :]).sum(-1) + 0.5
        rgb = torch.clamp(rgb, min=0.0)  # [G, 3]
        # A culled Gaussian's colour is never used; at the camera centre it is undefined (NaN).
        rgb = torch.where(valid[:, None], rgb, torch.zeros_like(rgb))

        order = torch.sort(torch.where(valid, z, torch.full_like(z, math.inf)), stable=True)[1]
        u, v, conic, z, radius, valid, rgb = (q[order] for q in (u, v, conic, z, radius, valid,
                                                                 rgb))
        opac = opacities[bi][order]
        dx = u[None, :] - pix_x[:, None]  # [P, G]
        dy = v[None, :] - pix_y[:, None]
        power = (-0.5 * (conic[None, :, 0] * dx * dx + conic[None, :, 2] * dy * dy)
                 - conic[None, :, 1] * dx * dy)
        raw = opac[None, :] * torch.exp(power)
        alpha = torch.clamp(raw, max=0.99)
        if clamp_gradient == "reference":
            alpha = raw + (alpha - raw).detach()
        use = valid[None, :] & (power <= 0) & (alpha >= 1.0 / 255.0)
        if tile_cut:
            px_c, py_c = u - 0.5, v - 0.5
            gx, gy = math.ceil(W / 16), math.ceil(H / 16)
            x0 = torch.clamp(torch.floor((px_c - radius) / 16), 0, gx)
            x1 = torch.clamp(torch.floor((px_c + radius + 15) / 16), 0, gx)
            y0 = torch.clamp(torch.floor((py_c - radius) / 16), 0, gy)
            y1 = torch.clamp(torch.floor((py_c + radius + 15) / 16), 0, gy)
            tx = torch.floor((pix_x - 0.5) / 16)[:, None]
            ty = torch.floor((pix_y - 0.5) / 16)[:, None]
            use = use & (tx >= x0[None]) & (tx < x1[None]) & (ty >= y0[None]) & (ty < y1[None])
        a_eff = torch.where(use, alpha, torch.zeros_like(alpha))
        T_after = torch.cumprod(1 - a_eff, dim=1)
        use = use & (T_after >= 1e-4)  # stop before the Gaussian that takes T below 1e-4
        a_eff = torch.where(use, alpha, torch.zeros_like(alpha))
        T_after = torch.cumprod(1 - a_eff, dim=1)
        T_before = torch.cat([torch.ones_like(T_after[:, :1]), T_after[:, :-1]], 1)
        w = a_eff * T_before
        T_final = T_after[:, -1] if T_after.shape[1] else torch.ones_like(pix_x)
        color = w @ rgb + T_final[:, None] * background[bi][None, :]
        colors.append(color.T.reshape(3, H, W))
        alphas.append((1 - T_final).reshape(H, W))
        depths.append((w @ z).reshape(H, W))
    return torch.stack(colors), torch.stack(alphas), torch.stack(depths)
