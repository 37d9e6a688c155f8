"""Plane-sweep cost volume in inverse depth (MVSplat ``depth_predictor_multiview.py`` and
UniMatch ``warp_with_pose_depth_candidates``), computed in chunks of depth candidates so the
warped feature volume [V*B, C, D, H, W] (512 MiB at 256x256) never exists at once.

Conventions kept on purpose, to reproduce the reference: integer pixel coordinates 0..w-1 (no
half-pixel offset), the reference view's intrinsics for back-projection and projection (all
views are assumed to share K), the projected depth clamped at 1e-3, ``grid_sample`` bilinear with
zero padding and ``align_corners=True``. No gradient flows into the cameras (as the reference).
"""

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor


def disparity_candidates(near: Float[Tensor, "b v"], far: Float[Tensor, "b v"], num: int
                         ) -> Float[Tensor, "vb d"]:
    """1/far + linspace(0, 1, num) * (1/near - 1/far), in (v b) order; index 0 is the far plane."""
    lo = (1.0 / far).t().reshape(-1, 1)
    hi = (1.0 / near).t().reshape(-1, 1)
    return lo + torch.linspace(0.0, 1.0, num, device=near.device)[None] * (hi - lo)


def relative_poses(extrinsics: Float[Tensor, "b v 4 4"]) -> list[Tensor]:
    """For each shift s = 1..V-1, the [(v b), 4, 4] poses taking view v's camera frame to view
    (v + s) mod V's: inv(E_{v+s}) E_v. With two views, computed as the reference does
    ([P, inv(P)] with P = inv(E1) E0), which is what its 2-view checkpoints saw."""
    b, v = extrinsics.shape[:2]  # noqa: RUF059 (unpacked to name the shape)
    e = extrinsics.detach()
    if v == 2:
        pose = e[:, 1].inverse() @ e[:, 0]
        return [torch.cat((pose, pose.inverse()), dim=0)]
    poses = []
    for s in range(1, v):
        order = [(i + s) % v for i in range(v)]
        poses.append(torch.cat([e[:, j].inverse() @ e[:, i] for i, j in enumerate(order)], 0))
    return poses


def pixel_intrinsics(intrinsics: Float[Tensor, "b v 3 3"], h: int, w: int
                     ) -> Float[Tensor, "vb 3 3"]:
    """Normalised intrinsics to feature-map pixels (row 0 x w, row 1 x h), (v b) order."""
    k = intrinsics.detach().clone()
    k[:, :, 0, :] *= float(w)
    k[:, :, 1, :] *= float(h)
    return k.transpose(0, 1).reshape(-1, 3, 3)


def warp_grid(pose: Float[Tensor, "n 4 4"], k: Float[Tensor, "n 3 3"],
              depth: Float[Tensor, "n d"], h: int, w: int) -> Float[Tensor, "n d hw 2"]:
    """grid_sample coordinates of each reference pixel at each candidate depth in the other
    view (align_corners=True normalisation)."""
    n, d = depth.shape
    ys, xs = torch.meshgrid(torch.arange(h, device=k.device), torch.arange(w, device=k.device),
                            indexing="ij")
    grid = torch.stack([xs, ys, torch.ones_like(xs)], 0).float().view(1, 3, -1).expand(n, 3, -1)
    points = torch.inverse(k).bmm(grid)  # [N, 3, HW]
    points = torch.bmm(pose[:, :3, :3], points).unsqueeze(2) * depth.view(n, 1, d, 1)
    points = points + pose[:, :3, 3:].unsqueeze(-1)  # [N, 3, D, HW]
    points = torch.bmm(k, points.reshape(n, 3, -1)).view(n, 3, d, h * w)
    pix = points[:, :2] / points[:, 2:].clamp(min=1e-3)
    return torch.stack([2 * pix[:, 0] / (w - 1) - 1, 2 * pix[:, 1] / (h - 1) - 1], dim=-1)


def _correlation_warp(ref: Tensor, other: Tensor, grid: Tensor, chunk: int) -> Tensor:
    """<ref, grid_sample(other)> per candidate, ``chunk`` candidates warped at a time: the
    reference's computation, with peak extra memory N*C*chunk*H*W floats instead of all D."""
    n, c, h, w = ref.shape
    parts = []
    for d0 in range(0, grid.shape[1], chunk):
        g = grid[:, d0:d0 + chunk]
        dc = g.shape[1]
        warped = F.grid_sample(other, g.reshape(n, dc * h, w, 2), mode="bilinear",
                               padding_mode="zeros", align_corners=True).view(n, c, dc, h, w)
        parts.append((ref.unsqueeze(2) * warped).sum(1))
    return torch.cat(parts, dim=1)


def _bilinear_corners(grid: Tensor, h: int, w: int) -> tuple[list[Tensor], list[Tensor]]:
    """The 4 bilinear corners of ``grid``'s points (align_corners=True normalisation) as flat
    pixel indices, and their weights (0 outside the image: zero padding), each [N, D, P]."""
    # normalised -> pixel coordinates; clamp far-off points (their corners are all outside
    # anyway) so floor() stays in integer range.
    x = ((grid[..., 0] + 1) * (w - 1) / 2).clamp(-2, w + 1)  # [N, D, P]
    y = ((grid[..., 1] + 1) * (h - 1) / 2).clamp(-2, h + 1)
    x0, y0 = x.floor(), y.floor()
    fx, fy = x - x0, y - y0
    corners, weights = [], []
    for dy, dx, wgt in ((0, 0, (1 - fx) * (1 - fy)), (0, 1, fx * (1 - fy)),
                        (1, 0, (1 - fx) * fy), (1, 1, fx * fy)):
        xi, yi = x0 + dx, y0 + dy
        inside = (xi >= 0) & (xi <= w - 1) & (yi >= 0) & (yi <= h - 1)
        corners.append((yi.clamp(0, h - 1) * w + xi.clamp(0, w - 1)).long())
        weights.append(torch.where(inside, wgt, torch.zeros_like(wgt)))
    return corners, weights


def _correlation_gram(ref: Tensor, other: Tensor, grid: Tensor, max_bytes: int) -> Tensor:
    """The same correlation from dot products: bilinear sampling is linear, so
    <f_ref(p), sum_k w_k f_other(q_k)> = sum_k w_k <f_ref(p), f_other(q_k)>. One matmul gives
    G[p, q] = <f_ref(p), f_other(q)> for all pixel pairs (rows in chunks of at most
    ``max_bytes``), then each candidate gathers its 4 bilinear corners from G. About 10x less
    work than warping C channels D times; zero padding = corners outside the image weigh 0.
    The corners are computed chunk by chunk too (all at once they would take 12 bytes per
    pixel, candidate and corner: 48 MiB at 2x64x64 features and 128 candidates)."""
    n, c, h, w = ref.shape
    d = grid.shape[1]
    hw = h * w
    ref_t = ref.reshape(n, c, hw).transpose(1, 2)  # [N, HW, C]
    other_f = other.reshape(n, c, hw)
    rows = max(1, min(hw, max_bytes // (4 * hw * max(n, 1))))
    out = []
    for p0 in range(0, hw, rows):
        with torch.no_grad():
            corners, weights = _bilinear_corners(grid[:, :, p0:p0 + rows], h, w)
        gram = torch.bmm(ref_t[:, p0:p0 + rows], other_f)  # [N, P, HW]
        acc = None
        for idx, wgt in zip(corners, weights):
            term = torch.gather(gram, 2, idx.transpose(1, 2)) * wgt.transpose(1, 2)  # [N, P, D]
            acc = term if acc is None else acc + term
        out.append(acc)
    return torch.cat(out, dim=1).transpose(1, 2).reshape(n, d, h, w)


def plane_sweep_correlation(features: Float[Tensor, "b v c h w"],
                            extrinsics: Float[Tensor, "b v 4 4"],
                            intrinsics: Float[Tensor, "b v 3 3"],
                            disparities: Float[Tensor, "vb d"],
                            method: str = "gram", chunk: int = 16,
                            max_bytes: int = 64 * 2**20) -> Float[Tensor, "vb d h w"]:
    """Mean over the other views of <f_ref, warp(f_other, depth)> / sqrt(C) per candidate, in
    (v b) order. ``method="gram"`` (default) from pixel-pair dot products, ``"warp"`` by
    warping ``chunk`` candidates at a time as the reference does; both agree to float32
    rounding and neither holds the full warped volume [V*B, C, D, H, W]."""
    if method not in ("gram", "warp"):
        raise ValueError(f"method must be 'gram' or 'warp', got {method!r}")
    b, v, c, h, w = features.shape
    ref = features.transpose(0, 1).reshape(v * b, c, h, w)
    k = pixel_intrinsics(intrinsics, h, w)
    depth = 1.0 / disparities
    total = None
    for s, pose in enumerate(relative_poses(extrinsics), start=1):
        order = [(i + s) % v for i in range(v)]
        other = features[:, order].transpose(0, 1).reshape(v * b, c, h, w)
        # Geometry in float32 whatever autocast says: in bfloat16 the pixel coordinates round
        # by up to a pixel and the gathered corner indices run past the image.
        with torch.no_grad(), torch.autocast(k.device.type, enabled=False):
            grid = warp_grid(pose.float(), k.float(), depth.detach().float(), h, w)
        if method == "gram":
            corr = _correlation_gram(ref, other, grid, max_bytes)
        else:
            corr = _correlation_warp(ref, other, grid, chunk)
        total = corr if total is None else total + corr
    return total / (c**0.5 * (v - 1))
