"""SH rotation checked by its defining property, on directions it was not fitted on."""

import math

import torch

from usplat_dr.model.sh_rotation import real_sh, rotate_sh, wigner_d
from usplat_dr.render.sh import C1, C2, C3


def random_rotation(seed: int) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(seed),
                                       dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def unit(n: int, seed: int) -> torch.Tensor:
    d = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return d / d.norm(dim=-1, keepdim=True)


def test_basis_is_orthonormal():
    # Integral normalisation: a Monte-Carlo estimate of <Y_i, Y_j> over the sphere is
    # 4 pi E[Y_i Y_j]; 200k samples give ~1e-2 accuracy.
    y = real_sh(unit(200_000, 1), 4)
    gram = 4 * math.pi * y.T @ y / y.shape[0]
    assert torch.allclose(gram, torch.eye(25, dtype=torch.float64), atol=3e-2)


def test_degrees_0_to_3_are_the_renderers_basis_up_to_sign():
    # docs/mvsplat_notes.md sec. 3: MVSplat's rasteriser basis is (-1)^i e3nn Y_i (except its
    # coefficient-14 anomaly) = the 3DGS basis at (z, x, y): an independent formula.
    d = unit(50, 2)
    x, y, z = d[:, 2], d[:, 0], d[:, 1]  # the 3DGS formulas at (z, x, y)
    xx, yy, zz = x * x, y * y, z * z
    std = [torch.full_like(x, 0.28209479177387814), -C1 * y, C1 * z, -C1 * x,
           C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z,
           C2[4] * (xx - yy), C3[0] * y * (3 * xx - yy), C3[1] * x * y * z,
           C3[2] * y * (4 * zz - xx - yy), C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
           C3[4] * x * (4 * zz - xx - yy), C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy)]
    ours = real_sh(d, 3)
    for i, s in enumerate(std):
        assert torch.allclose((-1) ** i * ours[:, i], s, atol=1e-12), i


def test_wigner_d_is_equivariant_and_a_representation():
    r1, r2 = random_rotation(3), random_rotation(4)
    d = unit(100, 5)
    for deg, dl in enumerate(wigner_d(r1, 4)):
        sl = slice(deg * deg, (deg + 1) ** 2)
        # Y(R d) = D(R) Y(d) on fresh directions (float64 least squares: ~1e-13).
        assert torch.allclose(real_sh(d @ r1.T, 4)[:, sl], real_sh(d, 4)[:, sl] @ dl.T,
                              atol=1e-10), deg
        composed = wigner_d(r1 @ r2, 4)[deg]
        assert torch.allclose(composed, dl @ wigner_d(r2, 4)[deg], atol=1e-10)


def test_rotated_function_takes_the_same_values_at_rotated_directions():
    r = random_rotation(6)
    sh = torch.randn(3, 25, dtype=torch.float64)
    d = unit(64, 7)
    before = (real_sh(d, 4)[:, None] * sh).sum(-1)  # f(d) per colour
    after = (real_sh(d @ r.T, 4)[:, None] * rotate_sh(sh, r)).sum(-1)  # f'(R d)
    assert torch.allclose(before, after, atol=1e-10)


def test_one_rotation_per_camera_broadcasts():
    r = torch.stack([random_rotation(8), random_rotation(9)]).float()  # [V, 3, 3]
    sh = torch.randn(2, 5, 3, 16)
    out = rotate_sh(sh, r[:, None, None])
    assert torch.allclose(out[1, 3], rotate_sh(sh[1, 3], r[1]), atol=1e-6)
