"""Conversions between Mitsuba and usplat-dr: the perspective sensor as our camera, Mitsuba
``ellipsoids`` shapes as Gaussians (Dr.Jit arrays, differentiable), and the model's Gaussians
(torch) as an ``ellipsoids`` shape and back.

Conventions. Mitsuba's ``ellipsoids`` shape stores per ellipsoid ``center`` (3), ``scale``
(3, standard deviations: volprim's kernel is exp(-0.5 |R^T (p - c) / s|^2)) and a unit
quaternion (x, y, z, w) in its ``data`` parameter; ``opacities`` (1) and ``sh_coeffs`` (3 x D,
coefficient-major: coefficient i of channel j at i * 3 + j) are attributes, as Mitsuba's
``volprim_rf_basic`` integrator reads them. Its SH basis, ``dr.sh_eval``, is the 3DGS basis
(tested), evaluated at the direction from the camera centre to the centre, colour = SH + 0.5
clamped at 0.
"""

import math

import drjit as dr
import mitsuba as mi
import numpy as np

#: Mitsuba's camera space (x left, y up, z forward) to OpenCV's (x right, y down, z forward).
FLIP_XY = np.diag([-1.0, -1.0, 1.0, 1.0])


def sensor_camera(sensor) -> dict:
    """Our camera for a Mitsuba ``perspective`` sensor: ``extrinsics`` (4x4 camera-to-world,
    OpenCV axes), ``intrinsics`` (3x3, normalised by the rendered width and height),
    ``near``, ``far`` and ``image_shape`` (H, W) of the film's crop window (what ``mi.render``
    returns). The field of view (any ``fov_axis``), crop window and principal point offsets
    are read from the sensor's own projection, so they follow Mitsuba's definitions."""
    if not sensor.class_name().startswith("PerspectiveCamera"):
        raise ValueError(f"usplat_splat renders through a 'perspective' sensor, got "
                         f"{sensor.class_name()}; use type='perspective' (no depth of field)")
    film = sensor.film()
    crop = film.crop_size()
    proj = np.array(sensor.projection_transform().matrix, dtype=np.float64).reshape(4, 4)
    params = mi.traverse(sensor)
    ox = float(dr.ravel(params["principal_point_offset_x"])[0])
    oy = float(dr.ravel(params["principal_point_offset_y"])[0])
    # sample u = (M00 X + M02 Z) / Z over the crop, and the sensor traces the sample u
    # shifted by the offset, which is in units of the whole film (measured against Mitsuba's
    # rays in tests/test_plugins.py): with x_cv = -X, u = -M00 x_cv / z + M02 - ox W / W_crop
    size = film.size()
    ox *= size[0] / crop[0]
    oy *= size[1] / crop[1]
    intrinsics = np.array([[-proj[0, 0], 0.0, proj[0, 2] - ox],
                           [0.0, -proj[1, 1], proj[1, 2] - oy],
                           [0.0, 0.0, 1.0]])
    to_world = np.array(sensor.world_transform().matrix, dtype=np.float64).reshape(4, 4)
    return {"extrinsics": to_world @ FLIP_XY, "intrinsics": intrinsics,
            "near": float(sensor.near_clip()), "far": float(sensor.far_clip()),
            "image_shape": (int(crop[1]), int(crop[0]))}


def ellipsoid_parameters(shape) -> dict:
    """The ``data``, ``opacities`` and ``sh_coeffs`` of an ``ellipsoids`` shape as its own
    (possibly AD-attached) Dr.Jit arrays, with the count and SH size checked."""
    params = mi.traverse(shape)
    keys = set(params.keys())
    missing = [k for k in ("data", "opacities", "sh_coeffs") if k not in keys]
    if missing:
        raise ValueError(f"ellipsoids shape {shape.id()!r} lacks {missing}: give it "
                         f"'opacities' [N, 1] and 'sh_coeffs' [N, 3 (degree + 1)^2] tensors "
                         f"(usplat_dr.plugins.gaussians_to_ellipsoids makes the dict)")
    data, opacity, sh = params["data"], params["opacities"], params["sh_coeffs"]
    n = dr.width(data) // 10
    if dr.width(data) != 10 * n or dr.width(opacity) != n:
        raise ValueError(f"ellipsoids shape {shape.id()!r}: {dr.width(data)} data values and "
                         f"{dr.width(opacity)} opacities for {n} ellipsoids")
    d = dr.width(sh) // (3 * n) if n else 1
    if dr.width(sh) != 3 * n * d or math.isqrt(d) ** 2 != d or d > 16:
        raise ValueError(f"ellipsoids shape {shape.id()!r}: sh_coeffs must hold 3 x (degree "
                         f"+ 1)^2 values per ellipsoid (degree 0..3), got {dr.width(sh)} for "
                         f"{n}")
    return {"data": data, "opacities": opacity, "sh_coeffs": sh, "count": n, "sh_size": d}


def ellipsoids_as_gaussians(shapes: list) -> dict:
    """The Gaussians of ``ellipsoids`` shapes, concatenated, as Dr.Jit arrays in our layout:
    ``means`` [G * 3], ``covariances`` [G * 9], ``sh`` [G * 3 * D] (channel-major) and
    ``opacities`` [G]. Differentiable with respect to the shapes' parameters."""
    parts = [ellipsoid_parameters(s) for s in shapes]
    d = max((p["sh_size"] for p in parts), default=1)
    means, covs, shs, ops = [], [], [], []
    for p in parts:
        n = p["count"]
        if n == 0:
            continue
        Float, UInt32 = mi.Float, mi.UInt32
        idx = dr.arange(UInt32, n)
        f = [dr.gather(Float, p["data"], idx * 10 + k) for k in range(10)]
        c, s, q = f[0:3], f[3:6], f[6:10]
        # rotation of the normalised quaternion (x, y, z, w: Dr.Jit's order, as volprim reads
        # it; 3DGS normalises too), covariance R diag(s^2) R^T
        quat = mi.Quaternion4f(*q)
        quat *= dr.rsqrt(dr.maximum(dr.squared_norm(quat), 1e-20))  # a zero one: no NaN
        r = dr.quat_to_matrix(mi.Matrix3f, quat)
        s2 = [si * si for si in s]
        cov = [sum(r[i, k] * s2[k] * r[j, k] for k in range(3)) for i in range(3)
               for j in range(3)]
        sh = [dr.gather(Float, p["sh_coeffs"], idx * (3 * p["sh_size"]) + i * 3 + ch)
              if i < p["sh_size"] else dr.zeros(Float, n)
              for ch in range(3) for i in range(d)]
        means.append(c)
        covs.append(cov)
        shs.append(sh)
        ops.append(p["opacities"])
    if not means:
        return {"count": 0, "sh_size": d}
    return {"means": _interleave([_concat([m[k] for m in means]) for k in range(3)]),
            "covariances": _interleave([_concat([c[k] for c in covs]) for k in range(9)]),
            "sh": _interleave([_concat([s[k] for s in shs]) for k in range(3 * d)]),
            "opacities": _concat(ops), "count": sum(p["count"] for p in parts), "sh_size": d}


def _concat(arrays: list):
    if len(arrays) == 1:
        return arrays[0]
    return dr.concat(arrays)


def _interleave(components: list):
    """[x0, x1, ..] (each [G]) -> [G * K] with component k of element g at g * K + k."""
    k = len(components)
    n = dr.width(components[0])
    out = dr.zeros(mi.Float, n * k)
    idx = dr.arange(mi.UInt32, n) * k
    for i, c in enumerate(components):
        dr.scatter(out, c, idx + i)
    return out


# ---- torch <-> Mitsuba ----------------------------------------------------------------------

def gaussians_to_ellipsoids(means, scales, rotations_xyzw, opacities, harmonics,
                            sh_basis: str = "mvsplat") -> dict:
    """A Mitsuba ``ellipsoids`` shape dict (``mi.load_dict`` it, or put it in a scene dict)
    from one set of Gaussians (torch or numpy, no batch): ``means`` [G, 3], ``scales`` [G, 3]
    (standard deviations), ``rotations_xyzw`` [G, 4] (world frame), ``opacities`` [G],
    ``harmonics`` [G, 3, D]. ``sh_basis``: the basis of ``harmonics`` ("mvsplat": the model's,
    converted to 3DGS's; "3dgs": as is). Degree 4 coefficients are dropped (no rasteriser
    evaluates them). See ``model_gaussians_to_ellipsoids`` for a model's output."""
    import torch  # only for torch tensors: the plugin itself runs on Mitsuba alone

    h = torch.as_tensor(_np(harmonics), dtype=torch.float64)
    if sh_basis == "mvsplat":
        from usplat_dr.model.ply import sh_to_3dgs  # loads torch: only for this basis

        h = sh_to_3dgs(h)
    elif sh_basis != "3dgs":
        raise ValueError(f"sh_basis must be 'mvsplat' or '3dgs', got {sh_basis!r}")
    h = h[..., :16].numpy()
    d = h.shape[-1]
    g = h.shape[0]
    sh = np.ascontiguousarray(h.transpose(0, 2, 1).reshape(g, 3 * d), dtype=np.float32)
    return {"type": "ellipsoids",
            "centers": mi.TensorXf(_np(means).astype(np.float32).reshape(g, 3)),
            "scales": mi.TensorXf(_np(scales).astype(np.float32).reshape(g, 3)),
            "quaternions": mi.TensorXf(_np(rotations_xyzw).astype(np.float32).reshape(g, 4)),
            "opacities": mi.TensorXf(_np(opacities).astype(np.float32).reshape(g, 1)),
            "sh_coeffs": mi.TensorXf(sh)}


def model_gaussians_to_ellipsoids(gaussians) -> dict:
    """The ``ellipsoids`` dict for one target's Gaussians of a ``UniqueSplatOutput``
    (``out.target(b, n)``, batch 1): the world-frame scales and rotations come from the
    covariances (eigen-decomposition), the SH from MVSplat's basis to 3DGS's."""
    import torch  # only for torch tensors: the plugin itself runs on Mitsuba alone

    from usplat_dr.geometry.quaternions import matrix_to_quat_wxyz  # torch (see above)

    cov = gaussians.covariances[0].detach().double().cpu()
    evals, evecs = torch.linalg.eigh(cov)
    det = torch.linalg.det(evecs)
    evecs = evecs * torch.where(det < 0, -1.0, 1.0)[:, None, None]  # proper rotations
    wxyz = matrix_to_quat_wxyz(evecs.numpy())
    return gaussians_to_ellipsoids(
        gaussians.means[0].detach().cpu(), evals.clamp(min=0).sqrt(),
        np.concatenate([wxyz[:, 1:], wxyz[:, :1]], -1), gaussians.opacities[0].detach().cpu(),
        gaussians.harmonics[0].detach().cpu(), sh_basis="mvsplat")


def ellipsoids_to_gaussians(shape) -> dict:
    """torch tensors (no batch) from an ``ellipsoids`` shape: ``means`` [G, 3],
    ``covariances`` [G, 3, 3], ``harmonics`` [G, 3, D] (3DGS basis), ``opacities`` [G];
    what ``usplat_dr.render.rasterize`` takes (with a batch dimension added)."""
    import torch  # only for torch tensors: the plugin itself runs on Mitsuba alone

    with dr.suspend_grad():
        g = ellipsoids_as_gaussians([shape])
    n, d = g["count"], g["sh_size"]
    if n == 0:
        raise ValueError(f"ellipsoids shape {shape.id()!r} holds no ellipsoids")
    return {"means": torch.tensor(np.array(g["means"])).view(n, 3),
            "covariances": torch.tensor(np.array(g["covariances"])).view(n, 3, 3),
            "harmonics": torch.tensor(np.array(g["sh"])).view(n, 3, d),
            "opacities": torch.tensor(np.array(g["opacities"])).view(n)}


def _np(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)
