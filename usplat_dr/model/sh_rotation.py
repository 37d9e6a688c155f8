"""Rotation of real spherical-harmonics coefficients, as MVSplat's ``rotate_sh`` (e3nn Wigner-D).

e3nn's real SH of degree l, order m (index l^2 + l + m) are the textbook real SH (no
Condon-Shortley phase) evaluated at the permuted direction (z, x, y): e3nn's "up" axis is y.
A rotation R acts on them by the matrix D_l(R) with Y_l(R d) = D_l(R) Y_l(d), so a function with
camera-frame coefficients c has world-frame coefficients D_l(R_c2w) c.

Instead of e3nn's Euler-angle construction (``matrix_to_angles`` + ``matrix_exp`` of the
generators) we solve that defining relation directly: D_l(R) = Y_l(R X) pinv(Y_l(X)) for a fixed
set X of directions (least squares that is exact, since the relation holds at every point).
It is computed once per camera, not once per Gaussian (the reference does the latter).
"""

import functools
import math

import torch
from jaxtyping import Float
from torch import Tensor


def real_sh(d: Float[Tensor, "*batch 3"], degree: int) -> Float[Tensor, "*batch n"]:
    """Real SH in e3nn's order and 'integral' normalisation, degrees 0..``degree`` (<= 4), at
    unit directions ``d`` = (x, y, z); n = (degree + 1)^2."""
    # Textbook real SH at (X, Y, Z) = (z, x, y).
    X, Y, Z = d[..., 2], d[..., 0], d[..., 1]
    out = [torch.full_like(X, 0.5 / math.sqrt(math.pi))]
    if degree >= 1:
        c1 = math.sqrt(3 / (4 * math.pi))
        out += [c1 * Y, c1 * Z, c1 * X]
    if degree >= 2:
        XX, YY, ZZ = X * X, Y * Y, Z * Z
        out += [1.0925484305920792 * X * Y, 1.0925484305920792 * Y * Z,
                0.31539156525252005 * (2 * ZZ - XX - YY), 1.0925484305920792 * X * Z,
                0.5462742152960396 * (XX - YY)]
    if degree >= 3:
        out += [0.5900435899266435 * Y * (3 * XX - YY), 2.890611442640554 * X * Y * Z,
                0.4570457994644658 * Y * (4 * ZZ - XX - YY),
                0.3731763325901154 * Z * (2 * ZZ - 3 * XX - 3 * YY),
                0.4570457994644658 * X * (4 * ZZ - XX - YY), 1.445305721320277 * Z * (XX - YY),
                0.5900435899266435 * X * (XX - 3 * YY)]
    if degree >= 4:
        out += [2.5033429417967046 * X * Y * (XX - YY),
                1.7701307697799304 * Y * Z * (3 * XX - YY),
                0.9461746957575601 * X * Y * (7 * ZZ - 1),
                0.6690465435572892 * Y * Z * (7 * ZZ - 3),
                0.10578554691520431 * (35 * ZZ * ZZ - 30 * ZZ + 3),
                0.6690465435572892 * X * Z * (7 * ZZ - 3),
                0.47308734787878004 * (XX - YY) * (7 * ZZ - 1),
                1.7701307697799304 * X * Z * (XX - 3 * YY),
                0.6258357354491761 * (XX * (XX - 3 * YY) - YY * (3 * XX - YY))]
    if degree > 4:
        raise ValueError(f"degree must be <= 4, got {degree}")
    return torch.stack(out, dim=-1)


def fibonacci_sphere(n: int) -> Float[Tensor, "n 3"]:
    """``n`` nearly uniform unit directions (a Fibonacci lattice), float64."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    r = (1 - z * z).sqrt()
    return torch.stack([r * phi.cos(), r * phi.sin(), z], -1)


@functools.lru_cache(maxsize=8)
def _probe(degree: int) -> tuple[Tensor, list[Tensor]]:
    """Probe directions (64 on a Fibonacci sphere, enough for degree 4) and, per degree, the
    pseudo-inverse of their SH values, float64 on the CPU."""
    dirs = fibonacci_sphere(64)
    y = real_sh(dirs, degree)
    return dirs, [torch.linalg.pinv(y[:, deg * deg:(deg + 1) ** 2])
                  for deg in range(degree + 1)]


def wigner_d(rotation: Float[Tensor, "*batch 3 3"], degree: int) -> list[Tensor]:
    """[D_0(R), ..., D_degree(R)], each [*batch, 2l+1, 2l+1], in float64."""
    dirs, pinvs = _probe(degree)
    r = rotation.to(torch.float64)
    rotated = torch.einsum("...ij,nj->...ni", r, dirs.to(r.device))
    y = real_sh(rotated, degree)  # [*batch, N, n_sh]
    return [(pinvs[deg].to(r.device) @ y[..., deg * deg:(deg + 1) ** 2]).transpose(-1, -2)
            for deg in range(degree + 1)]


def sh_rotation_matrix(rotation: Float[Tensor, "*batch 3 3"], degree: int,
                       dtype: torch.dtype = torch.float32) -> Float[Tensor, "*batch n n"]:
    """The block-diagonal matrix diag(D_0(R), ..., D_degree(R)) that maps coefficients
    (e3nn's order, n = (degree + 1)^2) to those of the function rotated by ``rotation``."""
    n = (degree + 1) ** 2
    full = rotation.new_zeros(*rotation.shape[:-2], n, n, dtype=dtype)
    for deg, d in enumerate(wigner_d(rotation, degree)):
        full[..., deg * deg:(deg + 1) ** 2, deg * deg:(deg + 1) ** 2] = d.to(dtype)
    return full


def rotate_sh(sh: Float[Tensor, "*batch n"], rotation: Float[Tensor, "*#batch 3 3"]
              ) -> Float[Tensor, "*batch n"]:
    """Coefficients of the function rotated by ``rotation`` (e3nn's convention: coefficient l^2
    + deg + m; n = (degree + 1)^2). ``rotation`` broadcasts against ``sh``'s batch dimensions;
    give it one matrix per camera, not per Gaussian.

    Examples:
        >>> import torch
        >>> sh = torch.randn(2, 25)
        >>> torch.allclose(rotate_sh(sh, torch.eye(3)), sh, atol=1e-6)
        True
    """
    n = sh.shape[-1]
    degree = math.isqrt(n) - 1
    if (degree + 1) ** 2 != n:
        raise ValueError(f"sh must have (degree+1)^2 coefficients, got {n}")
    batch = sh.shape[:-1]
    rb = (1,) * (len(batch) - (rotation.ndim - 2)) + tuple(rotation.shape[:-2])
    # One block-diagonal D per rotation, applied to every coefficient vector that shares it
    # by one matrix product (the rotation's trailing broadcast dimensions folded into rows).
    k = len(rb)
    while k > 0 and rb[k - 1] == 1:
        k -= 1
    lead = torch.broadcast_shapes(batch[:k], rb[:k])
    rot = rotation.reshape(*rb, 3, 3)[(...,) + (0,) * (len(rb) - k) + (slice(None),) * 2]
    full = sh_rotation_matrix(rot.expand(*lead, 3, 3), degree, sh.dtype)
    rows = sh.expand(*lead, *batch[k:], n).reshape(*lead, -1, n)
    return (rows @ full.transpose(-1, -2)).reshape(*lead, *batch[k:], n)
