"""Gaussians in the standard 3DGS PLY layout (what common 3DGS viewers open), and back.

Binary little-endian ``vertex`` elements with float32 properties ``x y z nx ny nz f_dc_0..2
f_rest_0..44 opacity scale_0..2 rot_0..3``: opacity as a logit, log scales, unit quaternions
w x y z (world frame), SH coefficients of degree <= 3 in the 3DGS basis, ``f_rest``
channel-major (all of red's coefficients 1..15, then green's, then blue's), zero-padded to
degree 3.

The model predicts SH in MVSplat's basis (its modified rasteriser: the standard basis at the
permuted direction (z, x, y), with coefficient 14 evaluated as z (z^2 - x^2)). Both span the
same functions on the sphere up to degree 3, so ``sh_to_3dgs`` converts exactly with one
16 x 16 matrix, solved by least squares on probe directions; degree 4 (which no rasteriser
evaluates) is dropped.
"""

import functools
import os
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from usplat_dr.geometry.quaternions import matrix_to_quat_wxyz, quat_xyzw_to_matrix
from usplat_dr.io import atomic_open
from usplat_dr.model.sh_rotation import fibonacci_sphere
from usplat_dr.model.types import Gaussians
from usplat_dr.render.sh import sh_basis

REST = 45  # degree-3 layout: 15 coefficients x 3 channels


@functools.lru_cache(maxsize=4)
def _basis_change(degree: int) -> np.ndarray:
    """M with B_mvsplat(d) = M B_3dgs(d) on the unit sphere, (degree+1)^2 square, float64."""
    x, y, z = fibonacci_sphere(200).numpy().T
    k = (degree + 1) ** 2

    def values(basis):
        vals = sh_basis(x, y, z, degree, basis)
        return np.stack([np.broadcast_to(np.asarray(v, dtype=np.float64), x.shape)
                         for v in vals[:k]], 1)  # [n, k]

    std, mv = values("3dgs"), values("mvsplat")
    m, *_ = np.linalg.lstsq(std, mv, rcond=None)  # std @ m = mv  ->  B_mv = m^T B_std
    return m.T


def sh_to_3dgs(harmonics: Tensor) -> Tensor:
    """[G, 3, d_sh] coefficients of MVSplat's basis -> the 3DGS basis, degree <= 3."""
    d_sh = min(harmonics.shape[-1], 16)
    degree = int(d_sh**0.5) - 1
    m = torch.tensor(_basis_change(degree), dtype=harmonics.dtype, device=harmonics.device)
    # f = c_mv . B_mv = c_mv . (M B_std) = (M^T c_mv) . B_std
    return harmonics[..., :d_sh] @ m


def write_ply(path: str | os.PathLike, gaussians: Gaussians, sh_basis: str = "mvsplat",
              min_opacity: float = 0.0) -> Path:
    """Write the Gaussians of batch element 0 (atomically); ``sh_basis`` of their
    coefficients ("mvsplat" for the model's, "3dgs" for already standard ones)."""
    if sh_basis not in ("mvsplat", "3dgs"):
        raise ValueError(f"sh_basis must be 'mvsplat' or '3dgs', got {sh_basis!r}")
    keep = gaussians.opacities[0] > min_opacity
    cov = gaussians.covariances[0][keep].detach().double().cpu()
    sh = gaussians.harmonics[0][keep].detach().double().cpu()
    sh = sh_to_3dgs(sh) if sh_basis == "mvsplat" else sh[..., :16]
    evals, evecs = torch.linalg.eigh(cov)
    evecs = evecs * torch.where(torch.det(evecs) < 0, -1.0, 1.0)[:, None, None]  # proper
    scales = evals.clamp(min=1e-30).sqrt()
    op = gaussians.opacities[0][keep].detach().double().cpu().clamp(1e-7, 1 - 1e-7)
    g = len(cov)
    rest = np.zeros((g, 3, 15))
    rest[:, :, :sh.shape[-1] - 1] = sh[..., 1:].numpy()
    cols = {
        **{a: gaussians.means[0][keep][:, i].detach().cpu().numpy() for i, a in enumerate("xyz")},
        **{f"n{a}": np.zeros(g) for a in "xyz"},
        **{f"f_dc_{c}": sh[:, c, 0].numpy() for c in range(3)},
        **{f"f_rest_{i}": rest.reshape(g, REST)[:, i] for i in range(REST)},
        "opacity": torch.logit(op).numpy(),
        **{f"scale_{i}": scales[:, i].log().numpy() for i in range(3)},
        **{f"rot_{i}": q for i, q in enumerate(matrix_to_quat_wxyz(evecs.numpy()).T)},
    }
    data = np.empty(g, dtype=[(k, "<f4") for k in cols])
    for k, v in cols.items():
        data[k] = v
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {g}",
              *[f"property float {k}" for k in cols], "end_header"]
    with atomic_open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(data.tobytes())
    return Path(path)


def read_ply(path: str | os.PathLike) -> dict[str, Tensor]:
    """A 3DGS PLY as tensors: ``means`` [G,3], ``covariances`` [G,3,3], ``harmonics``
    [G,3,16] (3DGS basis), ``opacities`` [G], ``scales`` [G,3], ``rotations`` [G,4] (wxyz)."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:end].decode("ascii").splitlines()
    if header[:2] != ["ply", "format binary_little_endian 1.0"]:
        raise ValueError(f"{path}: not a binary little-endian PLY")
    names = [h.split()[2] for h in header if h.startswith("property float ")]
    if len(names) != len([h for h in header if h.startswith("property")]):
        raise ValueError(f"{path}: only float properties are supported")
    count = int(next(h for h in header if h.startswith("element vertex")).split()[2])
    data = np.frombuffer(raw[end:], dtype=[(k, "<f4") for k in names], count=count)

    def col(*keys):
        return torch.from_numpy(np.stack([data[k] for k in keys], 1).astype(np.float32))

    rest = col(*[f"f_rest_{i}" for i in range(REST)]).view(count, 3, 15)
    harmonics = torch.cat([col("f_dc_0", "f_dc_1", "f_dc_2")[:, :, None], rest], 2)
    scales = col("scale_0", "scale_1", "scale_2").exp()
    wxyz = col("rot_0", "rot_1", "rot_2", "rot_3")
    rot = quat_xyzw_to_matrix(torch.cat([wxyz[:, 1:], wxyz[:, :1]], 1))
    cov = rot @ torch.diag_embed(scales.square()) @ rot.transpose(1, 2)
    return {"means": col("x", "y", "z"), "covariances": cov, "harmonics": harmonics,
            "opacities": torch.sigmoid(col("opacity")[:, 0]), "scales": scales,
            "rotations": wxyz}
