"""Per-Gaussian stage: camera transform, EWA projection, culling and SH colour (Dr.Jit).

Conventions are those of the 3DGS CUDA rasteriser as pixelSplat/MVSplat call it (``render_cuda``
with ``scale_invariant=True``): see ``project()``. Plain vectorised Dr.Jit code over Gaussians,
differentiated by Dr.Jit AD.
"""

from dataclasses import dataclass

import drjit as dr

from usplat_dr.render.sh import eval_sh_color

#: Gaussians whose camera-space centre has z <= NEAR_CULL * near are culled (the reference's
#: ``p_view.z <= 0.2`` after scaling the scene by 1/near).
NEAR_CULL = 0.2
#: Low-pass filter added to the 2D covariance's diagonal (EWA antialiasing, 3DGS).
COV2D_DILATION = 0.3
#: The Jacobian's x/z and y/z are clamped to 1.3 x the half-extent of the view frustum.
FRUSTUM_GUARD = 1.3


@dataclass
class Camera:
    """One lane per Gaussian: the camera each Gaussian is rendered from.

    ``w2c_r`` (``list[list[Float]]``, 3x3 rows), ``w2c_t`` (``list[Float]``, 3): world-to-camera,
    OpenCV axes. ``fx, fy, cx, cy`` (``Float``): pixels. ``near`` (``Float``). ``centre``
    (``list[Float]``, 3): camera position in world space. ``width, height`` (``Float``): pixels.
    """

    w2c_r: list
    w2c_t: list
    fx: object
    fy: object
    cx: object
    cy: object
    near: object
    centre: list
    width: object
    height: object


@dataclass
class Projected:
    """Output of ``project()``, one lane per Gaussian.

    Differentiable: ``u, v`` (``Float``, pixels; pixel (i, j) is sampled at (j + 0.5, i + 0.5)),
    ``conic`` (``tuple[Float, Float, Float]``: a, b, c of the inverse 2D covariance
    [[a, b], [b, c]]), ``opacity`` (``Float``), ``rgb`` (``tuple`` of 3 ``Float``), ``z``
    (``Float``, camera-space depth of the centre). Not differentiable: ``cov2d`` (``tuple`` of 3
    ``Float``, the dilated 2D covariance xx, xy, yy), ``radius`` (``Float``, pixels, an integer
    value), ``valid`` (``Bool``).
    """

    u: object
    v: object
    conic: tuple
    opacity: object
    rgb: tuple
    z: object
    cov2d: tuple
    radius: object
    valid: object


def _matvec(m, v):
    return [dr.fma(m[i][0], v[0], dr.fma(m[i][1], v[1], m[i][2] * v[2])) for i in range(3)]


def project(means, cov6, opacities, sh, cam: Camera, sh_degree: int, sh_basis: str) -> Projected:
    """Project 3D Gaussians to the image plane (EWA splatting, Zwicker et al. 2002; Kerbl et al.
    2023, sec. 4), cull them as the reference does, and evaluate their colour.

    Parameter ``means`` (``list`` of 3 ``Float``, one lane per Gaussian): world-space centres.
    Parameter ``cov6`` (``list`` of 6 ``Float``): covariance entries xx, xy, xz, yy, yz, zz (the
    upper triangle, as the reference's ``cov3D_precomp``).
    Parameter ``opacities`` (``Float``). Parameter ``sh`` (``list[list[Float]]``, [3][D]).
    Parameter ``cam`` (``Camera``). ``sh_degree`` (``int``, 0..3), ``sh_basis`` (``str``).

    Scale invariance (``render_cuda``): the reference divides means and camera translation by
    near and covariances by near^2 before rasterising. The 2D covariance J W Sigma W^T J^T is
    invariant under that scaling (J scales by near, Sigma by 1/near^2) and so is the clamped
    x/z, so only the near-plane cull at z <= 0.2 (scaled) needs the factor: z <= 0.2 near.
    """
    # ---- Camera transform ----
    t = _matvec(cam.w2c_r, means)
    t = [t[i] + cam.w2c_t[i] for i in range(3)]
    valid = t[2] > NEAR_CULL * cam.near
    # Culled lanes still flow through AD (their gradient is zero): keep every value finite there
    # so that 0 * inf never turns a zero gradient into NaN.
    z = dr.select(valid, t[2], 1.0)
    inv_z = dr.rcp(z)
    x_z, y_z = t[0] * inv_z, t[1] * inv_z

    # ---- EWA projection ----
    # Clamp x/z, y/z to 1.3x the frustum's half-extent, per side so that an off-centre principal
    # point is honoured (for cx = W/2 this is the reference's 1.3 tan(fov_x / 2)).
    guard = FRUSTUM_GUARD - 1.0
    lim_x_pos = (cam.width - cam.cx + guard * 0.5 * cam.width) / cam.fx
    lim_x_neg = (cam.cx + guard * 0.5 * cam.width) / cam.fx
    lim_y_pos = (cam.height - cam.cy + guard * 0.5 * cam.height) / cam.fy
    lim_y_neg = (cam.cy + guard * 0.5 * cam.height) / cam.fy
    x_z_c = dr.clip(x_z, -lim_x_neg, lim_x_pos)
    y_z_c = dr.clip(y_z, -lim_y_neg, lim_y_pos)
    # J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]] with the clamped ratios; T = J R (2x3).
    j00, j02 = cam.fx * inv_z, -cam.fx * x_z_c * inv_z
    j11, j12 = cam.fy * inv_z, -cam.fy * y_z_c * inv_z
    r = cam.w2c_r
    t0 = [j00 * r[0][k] + j02 * r[2][k] for k in range(3)]
    t1 = [j11 * r[1][k] + j12 * r[2][k] for k in range(3)]
    xx, xy, xz, yy, yz, zz = cov6
    sigma = [[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]]
    s_t0 = _matvec(sigma, t0)
    s_t1 = _matvec(sigma, t1)
    a = dr.fma(t0[0], s_t0[0], dr.fma(t0[1], s_t0[1], t0[2] * s_t0[2])) + COV2D_DILATION
    b = dr.fma(t0[0], s_t1[0], dr.fma(t0[1], s_t1[1], t0[2] * s_t1[2]))
    c = dr.fma(t1[0], s_t1[0], dr.fma(t1[1], s_t1[1], t1[2] * s_t1[2])) + COV2D_DILATION

    # The reference drops det == 0 only; an indefinite 2D covariance (det < 0, from an invalid
    # non-positive-definite 3D covariance) has no ellipse and would make the radius NaN.
    det = a * c - b * b
    valid &= det > 0
    inv_det = dr.rcp(dr.select(valid, det, 1.0))
    conic = (c * inv_det, -b * inv_det, a * inv_det)

    a_d, b_d, c_d = dr.detach(a), dr.detach(b), dr.detach(c)
    mid = 0.5 * (a_d + c_d)
    lambda1 = mid + dr.sqrt(dr.maximum(0.1, mid * mid - dr.detach(det)))
    radius = dr.ceil(3.0 * dr.sqrt(dr.maximum(lambda1, 0.0)))
    valid &= dr.isfinite(radius)

    u = dr.fma(cam.fx, x_z, cam.cx)
    v = dr.fma(cam.fy, y_z, cam.cy)

    # ---- Colour (SH at the direction from the camera centre to the mean) ----
    d = [means[i] - cam.centre[i] for i in range(3)]
    norm2 = dr.fma(d[0], d[0], dr.fma(d[1], d[1], d[2] * d[2]))
    # A mean exactly at the camera centre has no direction; it is culled (z = 0) anyway.
    inv_norm = dr.rsqrt(dr.select(norm2 > 0, norm2, 1.0))
    rgb = tuple(eval_sh_color(sh, d[0] * inv_norm, d[1] * inv_norm, d[2] * inv_norm,
                              sh_degree, sh_basis))

    return Projected(u=u, v=v, conic=conic, opacity=opacities, rgb=rgb, z=z,
                     cov2d=(a_d, b_d, c_d), radius=radius, valid=valid)
