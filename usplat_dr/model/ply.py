"""Gaussians in the standard 3DGS PLY layout (what common 3DGS viewers open), and back.

Binary little-endian ``vertex`` elements with float32 properties ``x y z nx ny nz f_dc_0..2
f_rest_0..44 opacity scale_0..2 rot_0..3`` (the graphdeco layout): opacity as a logit, log
scales, unit quaternions w x y z (world frame), SH coefficients of degree <= 3 in the 3DGS
basis, ``f_rest`` channel-major (all of red's coefficients 1..15, then green's, then blue's),
zero-padded to degree 3 by the writer. ``read_ply`` also takes SH degrees 0-2 (0, 9 or 24
``f_rest`` properties) and ignores properties it does not use.

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
from usplat_dr.io.user_files import regular_file
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


# PLY scalar types -> numpy little-endian dtypes (both spellings of the PLY specification)
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2",
              "int16": "<i2", "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4",
              "uint": "<u4", "uint32": "<u4", "float": "<f4", "float32": "<f4",
              "double": "<f8", "float64": "<f8"}
_REST_DEGREE = {0: 0, 9: 1, 24: 2, 45: 3}  # number of f_rest properties -> SH degree
_REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
             "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def _vertex_layout(path, header: list[str]) -> tuple[np.dtype, int, int]:
    """(the vertex element's record dtype, its count, the bytes of the elements before it)."""
    if header[:2] != ["ply", "format binary_little_endian 1.0"]:
        fmt = header[1] if len(header) > 1 else "nothing"
        raise ValueError(f"{path}: a 3DGS PLY must be 'format binary_little_endian 1.0', "
                         f"this file has {fmt!r} (convert it, e.g. with plyfile)")
    elements: list[tuple[str, int, list]] = []
    for line in header[2:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info", "end_header"):
            continue
        if words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            if words[1:2] == ["list"]:
                raise ValueError(f"{path}: element {elements[-1][0]!r} has a list property "
                                 f"({line!r}); 3DGS files hold fixed-size records only")
            if len(words) != 3 or words[1] not in _PLY_TYPES:
                raise ValueError(f"{path}: unknown property declaration {line!r}")
            elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
        else:
            raise ValueError(f"{path}: malformed header line {line!r}")
    offset = 0
    for name, count, props in elements:
        names = [n for n, _ in props]
        if len(set(names)) != len(names):
            raise ValueError(f"{path}: element {name!r} declares a property twice ({names})")
        dtype = np.dtype(props)
        if name == "vertex":
            return dtype, count, offset
        offset += count * dtype.itemsize
    raise ValueError(f"{path}: no 'vertex' element (not a point cloud)")


#: Bytes a PLY may hold: 16M Gaussians of SH degree 3 (62 float32 each) are about 4 GB.
MAX_PLY_BYTES = 4 * 2**30
#: Bytes a PLY header may take (a 3DGS header is about 2 kB).
MAX_PLY_HEADER = 2**20


def read_ply(path: str | os.PathLike) -> dict:
    """A 3DGS PLY (graphdeco layout) as tensors: ``means`` [G,3], ``covariances``
    [G,3,3], ``harmonics`` [G,3,(D+1)^2] (3DGS basis), ``opacities`` [G], ``scales`` [G,3],
    ``rotations`` [G,4] (wxyz, as stored), and ``sh_degree`` D.

    The SH degree D is inferred from the number of ``f_rest_*`` properties (0, 9, 24 or 45
    for degree 0..3); properties other tools add (normals, colours, their own fields, of
    any scalar type) are ignored; every property is read as float32. Anything else (not a
    binary 3DGS PLY, truncated, a Gaussian with NaN or infinite values) is a ``ValueError``
    naming the file."""
    # a FIFO or /dev/zero: refused; then the header, then only the bytes it declares (a
    # sparse file claiming gigabytes is read to its vertices' end, never whole)
    path = regular_file(path, "PLY file", MAX_PLY_BYTES)
    with open(path, "rb") as f:
        head = f.read(MAX_PLY_HEADER)
        marker = head.find(b"end_header\n")
        if not head.startswith(b"ply") or marker < 0:
            raise ValueError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header' in "
                             f"its first {MAX_PLY_HEADER:,} bytes)")
        end = marker + len(b"end_header\n")
        try:
            header = head[:end].decode("ascii").splitlines()
        except UnicodeDecodeError:
            raise ValueError(f"{path}: the PLY header is not ASCII") from None
        dtype, count, offset = _vertex_layout(path, header)
        needed = end + offset + count * dtype.itemsize
        size = os.fstat(f.fileno()).st_size
        if needed > size:
            raise ValueError(f"{path}: truncated: the header declares {count} vertices "
                             f"({count * dtype.itemsize} bytes), the file holds "
                             f"{max(size - end - offset, 0)}")
        f.seek(0)
        raw = f.read(needed)
    names = dtype.names
    missing = [k for k in _REQUIRED if k not in names]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY, missing vertex properties {missing}")
    n_rest = sum(1 for k in names if k.startswith("f_rest_"))
    if n_rest not in _REST_DEGREE or any(f"f_rest_{i}" not in names for i in range(n_rest)):
        raise ValueError(f"{path}: {n_rest} f_rest_* properties; a 3DGS PLY has f_rest_0 .. "
                         f"f_rest_(N-1) with N = 0, 9, 24 or 45 (SH degree 0..3)")
    available = len(raw) - end - offset
    if available < count * dtype.itemsize:
        raise ValueError(f"{path}: truncated: the header declares {count} vertices "
                         f"({count * dtype.itemsize} bytes), the file holds {max(available, 0)}")
    data = np.frombuffer(raw, dtype=dtype, count=count, offset=end + offset)

    def col(*keys):
        stacked = np.stack([data[k] for k in keys], 1) if keys else np.zeros((count, 0))
        return torch.from_numpy(stacked.astype(np.float32))

    degree = _REST_DEGREE[n_rest]
    k = (degree + 1) ** 2
    rest = col(*[f"f_rest_{i}" for i in range(n_rest)]).view(count, 3, k - 1)
    harmonics = torch.cat([col("f_dc_0", "f_dc_1", "f_dc_2")[:, :, None], rest], 2)
    scales = col("scale_0", "scale_1", "scale_2").exp()
    wxyz = col("rot_0", "rot_1", "rot_2", "rot_3")
    rot = quat_xyzw_to_matrix(torch.cat([wxyz[:, 1:], wxyz[:, :1]], 1))  # divides out |q|
    cov = rot @ torch.diag_embed(scales.square()) @ rot.transpose(1, 2)
    out = {"means": col("x", "y", "z"), "covariances": cov, "harmonics": harmonics,
           "opacities": torch.sigmoid(col("opacity")[:, 0]), "scales": scales,
           "rotations": wxyz, "sh_degree": degree}
    # NaN or infinite values (a damaged file, or a diverged fit) would reach the rasteriser
    # unnoticed; so would a log scale over ~44 (its scale squared, in the covariance,
    # overflows float32). A zero quaternion is the identity here (quat_xyzw_to_matrix's eps).
    finite = [torch.isfinite(v).flatten(1).all(1) if v.ndim > 1 else torch.isfinite(v)
              for k, v in out.items() if k != "sh_degree"]
    bad = ~torch.stack(finite).all(0)
    if bad.any():
        raise ValueError(f"{path}: {int(bad.sum())} of {count} Gaussians have non-finite "
                         f"values (NaN or infinite, or a log scale too large for float32), "
                         f"the first at vertex {int(bad.nonzero()[0, 0])}")
    return out
