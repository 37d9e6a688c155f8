"""Dr.Jit entry point of the rasteriser: ``rasterize_drjit`` on ``TensorXf`` inputs.

The same computation as the torch entry ``usplat_dr.render.rasterize`` (which calls this through
``drjit.wrap``), for reuse without torch. The backend follows the inputs' type
(``drjit.llvm.ad`` or ``drjit.cuda.ad``). Stages: ``project`` -> ``tile_rects`` ->
``bin_gaussians`` -> ``Composite``; each is usable on its own.
"""

from dataclasses import dataclass, field

import drjit as dr

from usplat_dr.backend import module_of
from usplat_dr.render.binning import bin_gaussians, tile_rects
from usplat_dr.render.composite import Composite, PixelLanes
from usplat_dr.render.project import Camera, project
from usplat_dr.render.settings import RasterSettings
from usplat_dr.render.sh import sh_degree_for


@dataclass
class RenderOutputDr:
    """``color`` (``TensorXf`` [B, 3, H, W]), ``alpha`` (``TensorXf`` [B, H, W], 1 - final
    transmittance), ``depth`` (``TensorXf`` [B, H, W], sum of compositing weight x camera-space z
    of each Gaussian's centre; not divided by alpha; 0 on background). ``aux``: debug values
    (``num_pairs``, ``tile_size``, ``radii`` as ``Float`` per Gaussian, 0 where culled; with a
    ``pair_capacity``, ``num_pairs`` is ``None`` and ``overflow``, ``pairs_needed`` and
    ``pairs_kept`` are one-lane arrays, see ``binning.Bins``)."""

    color: object
    alpha: object
    depth: object
    aux: dict = field(default_factory=dict)


def check_shapes(image_shape, shapes: dict) -> tuple[int, int, int]:
    """Validate ``image_shape`` and the argument shapes of a render call; return (B, G, D).

    Parameter ``shapes`` (``dict``): argument name -> shape (any sequence of ints), for
    extrinsics, intrinsics, near, far, background_color, means, covariances, sh_coefficients and
    opacities. Shared by both entry points; raises ``ValueError`` naming the argument, what was
    expected (``*`` for a free size) and what came.
    """
    if (not isinstance(image_shape, (tuple, list)) or len(image_shape) != 2
            or not all(isinstance(s, int) and not isinstance(s, bool) and s > 0
                       for s in image_shape)):
        raise ValueError(f"image_shape must be (H, W) with positive ints, got {image_shape!r}")

    def expect(name, *expected):
        got = tuple(shapes[name])
        if len(got) != len(expected) or any(e is not None and e != g
                                            for e, g in zip(expected, got)):
            text = "(" + ", ".join("*" if e is None else str(e) for e in expected) + ")"
            raise ValueError(f"{name} must have shape {text}, got {got}")
        return got

    ext = tuple(shapes["extrinsics"])
    b = expect("extrinsics", ext[0] if len(ext) == 3 else None, 4, 4)[0]
    expect("intrinsics", b, 3, 3)
    expect("near", b)
    expect("far", b)
    expect("background_color", b, 3)
    g = expect("means", b, None, 3)[1]
    expect("covariances", b, g, 3, 3)
    d = expect("sh_coefficients", b, g, 3, None)[3]
    sh_degree_for(d)
    expect("opacities", b, g)
    return b, g, d


def check_inputs(extrinsics, intrinsics, near, far, image_shape, background_color, means,
                 covariances, sh_coefficients, opacities, check_values: bool = True):
    """Validate shapes (and, with ``check_values``, finiteness and near/far) of Dr.Jit tensors.

    Returns ``(B, G, D)``. Raises ``ValueError`` naming the argument, what was expected and what
    came. The torch entry point checks the same rules on torch tensors and skips these.
    """
    named = (("extrinsics", extrinsics), ("intrinsics", intrinsics), ("near", near),
             ("far", far), ("background_color", background_color), ("means", means),
             ("covariances", covariances), ("sh_coefficients", sh_coefficients),
             ("opacities", opacities))
    dims = check_shapes(image_shape, {name: t.shape for name, t in named})
    if check_values:
        for name, t in named:
            if dr.width(t.array) and not dr.all(dr.isfinite(dr.detach(t.array)), axis=None):
                raise ValueError(f"{name} must be finite, got NaN or Inf values")
        if not dr.all(dr.detach(near.array) > 0, axis=None):
            raise ValueError(f"near must be > 0, got {near.numpy()}")
        if not dr.all(dr.detach(far.array) > dr.detach(near.array), axis=None):
            raise ValueError(f"far must be > near, got near={near.numpy()} far={far.numpy()}")
    return dims


def _render_cuda_tan_fov(Float, k, idx):
    """``tan(fov / 2)`` per image as ``render_cuda`` derives it (pixelSplat's ``get_fov``):
    fov_x is the angle between the rays ``K^-1 (0, 0.5, 1)`` and ``K^-1 (1, 0.5, 1)`` through
    the left and right edge midpoints, fov_y the same for the top and bottom midpoints.
    Computed as ``|l x r| / (|l| |r| + l . r)`` (= tan of half the angle, without acos)."""
    m = [[dr.gather(Float, k, idx * 9 + (3 * i + j)) for j in range(3)] for i in range(3)]
    # K^-1 p is proportional to adj(K) p; the common factor 1 / det(K) cancels in the angle.
    adj = [[m[(j + 1) % 3][(i + 1) % 3] * m[(j + 2) % 3][(i + 2) % 3]
            - m[(j + 1) % 3][(i + 2) % 3] * m[(j + 2) % 3][(i + 1) % 3] for j in range(3)]
           for i in range(3)]

    def ray(u, v):
        return [adj[i][0] * u + adj[i][1] * v + adj[i][2] for i in range(3)]

    def tan_half_angle(a, b):
        cross = [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
        dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
        return dr.norm(cross) / (dr.norm(a) * dr.norm(b) + dot)

    return (tan_half_angle(ray(0.0, 0.5), ray(1.0, 0.5)),
            tan_half_angle(ray(0.5, 0.0), ray(0.5, 1.0)))


def _cameras(mod, extrinsics, intrinsics, near, width: int, height: int,
             projection: str = "intrinsics"):
    """Per-image camera values (one lane per image), detached: no gradients reach the cameras.
    ``projection``: ``RasterSettings.projection``."""
    Float, UInt32 = mod.Float, mod.UInt32
    b = extrinsics.shape[0]
    idx = dr.arange(UInt32, b)
    e = dr.detach(extrinsics.array)
    k = dr.detach(intrinsics.array)

    def ext(i, j):
        return dr.gather(Float, e, idx * 16 + (4 * i + j))

    r_c2w = [[ext(i, j) for j in range(3)] for i in range(3)]
    t_c2w = [ext(i, 3) for i in range(3)]
    w2c_r = [[r_c2w[j][i] for j in range(3)] for i in range(3)]  # R^T
    w2c_t = [-(w2c_r[i][0] * t_c2w[0] + w2c_r[i][1] * t_c2w[1] + w2c_r[i][2] * t_c2w[2])
             for i in range(3)]
    # Image size as opaque scalars: as literals each new resolution would recompile kernels.
    w_f, h_f = dr.opaque(Float, float(width)), dr.opaque(Float, float(height))
    if projection == "render_cuda":
        tan_x, tan_y = _render_cuda_tan_fov(Float, k, idx)
        fx, fy = w_f / (2.0 * tan_x), h_f / (2.0 * tan_y)  # focal_x = W / (2 tan(fov_x / 2))
        cx, cy = 0.5 * w_f, 0.5 * h_f  # a symmetric frustum: the image centre
    else:
        fx = dr.gather(Float, k, idx * 9 + 0) * w_f  # intrinsics are normalised by W (row 0)
        cx = dr.gather(Float, k, idx * 9 + 2) * w_f
        fy = dr.gather(Float, k, idx * 9 + 4) * h_f  # ... and by H (row 1)
        cy = dr.gather(Float, k, idx * 9 + 5) * h_f
    return Camera(w2c_r=w2c_r, w2c_t=w2c_t, fx=fx, fy=fy, cx=cx, cy=cy,
                  near=dr.detach(near.array), centre=t_c2w, width=w_f, height=h_f)


def _gather_camera(cam: Camera, batch) -> Camera:
    Float = type(cam.fx)

    def g(x):
        return dr.gather(Float, x, batch)

    return Camera(w2c_r=[[g(x) for x in row] for row in cam.w2c_r],
                  w2c_t=[g(x) for x in cam.w2c_t], fx=g(cam.fx), fy=g(cam.fy), cx=g(cam.cx),
                  cy=g(cam.cy), near=g(cam.near), centre=[g(x) for x in cam.centre],
                  width=cam.width, height=cam.height)


def pixel_lanes(mod, num_images: int, height: int, width: int, tile_size: int) -> PixelLanes:
    """Tile-major pixel lanes for ``num_images`` images of ``height`` x ``width``."""
    Float, UInt32 = mod.Float, mod.UInt32
    grid_x = -(-width // tile_size)
    grid_y = -(-height // tile_size)
    n = num_images * grid_x * grid_y * tile_size * tile_size
    gx, gy = dr.opaque(UInt32, grid_x), dr.opaque(UInt32, grid_y)
    w_u, h_u = dr.opaque(UInt32, width), dr.opaque(UInt32, height)
    lane = dr.arange(UInt32, n)
    shift = (tile_size * tile_size).bit_length() - 1
    tile = lane >> shift
    local = lane & (tile_size * tile_size - 1)
    ix = local & (tile_size - 1)
    iy = local >> (tile_size.bit_length() - 1)
    # Guarded divisors (opaque values; see binning.py on integer division).
    gx_safe, gy_safe = dr.maximum(gx, 1), dr.maximum(gy, 1)
    rest = tile // gx_safe
    tx = tile - rest * gx
    batch = rest // gy_safe
    ty = rest - batch * gy
    x = tx * tile_size + ix
    y = ty * tile_size + iy
    in_image = (x < w_u) & (y < h_u)
    hw = w_u * h_u
    row_major = y * w_u + x
    return PixelLanes(px=Float(x) + 0.5, py=Float(y) + 0.5, tile=tile, in_image=in_image,
                      pixel=batch * hw + row_major, color_index=batch * (3 * hw) + row_major,
                      batch=batch, hw=hw)


def rasterize_drjit(extrinsics, intrinsics, near, far, image_shape, background_color, means,
                    covariances, sh_coefficients, opacities,
                    settings: RasterSettings | None = None, check: bool = True,
                    pair_capacity: int | None = None) -> RenderOutputDr:
    """Render 3D Gaussians with the 3DGS CUDA rasteriser's rules, on Dr.Jit tensors.

    Arguments follow pixelSplat/MVSplat's ``render_cuda``, as ``TensorXf`` of one backend:
    ``extrinsics`` [B, 4, 4] camera-to-world, OpenCV axes (x right, y down, z forward);
    ``intrinsics`` [B, 3, 3] normalised (row 0 by width, row 1 by height; skew ignored);
    ``near``, ``far`` [B]; ``image_shape`` (H, W); ``background_color`` [B, 3];
    ``means`` [B, G, 3]; ``covariances`` [B, G, 3, 3] (the upper triangle is read, as the
    reference's ``cov3D_precomp``); ``sh_coefficients`` [B, G, 3, D], D = (degree + 1)^2;
    ``opacities`` [B, G]. ``far`` is validated but, as in the reference, culls nothing.

    Differentiable (Dr.Jit AD) with respect to means, covariances, SH coefficients and
    opacities; cameras get no gradient. ``check=False`` skips the value checks (NaN/Inf,
    near/far), which read values back to the host. ``pair_capacity`` (``int``): bin into that
    many (tile, Gaussian) pair lanes and read nothing back (with ``check=False``), so that
    ``dr.freeze`` can record the call; ``aux["overflow"]`` then says whether the scene needed
    more (its images miss pairs; ``aux["pairs_needed"]`` is how many), ``render.frozen``.

    Examples:
        >>> import drjit as dr, usplat_dr
        >>> from drjit.llvm.ad import TensorXf
        >>> from usplat_dr.render.pipeline import rasterize_drjit
        >>> eye = TensorXf([1.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1], shape=(1, 4, 4))
        >>> K = TensorXf([1.0, 0, 0.5, 0, 1, 0.5, 0, 0, 1], shape=(1, 3, 3))
        >>> out = rasterize_drjit(eye, K, TensorXf([0.1], shape=(1,)), TensorXf([10.0], shape=(1,)),
        ...     (8, 8), TensorXf([0.0, 0, 0], shape=(1, 3)), TensorXf([0.0, 0, 2], shape=(1, 1, 3)),
        ...     TensorXf([0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.01], shape=(1, 1, 3, 3)),
        ...     TensorXf([1.0, 1, 1], shape=(1, 1, 3, 1)), TensorXf([0.9], shape=(1, 1)))
        >>> out.color.shape, round(float(out.alpha.numpy()[0, 3, 3]), 2)
        ((1, 3, 8, 8), 0.52)
    """
    settings = settings or RasterSettings()
    if pair_capacity is not None and (isinstance(pair_capacity, bool)
                                      or not isinstance(pair_capacity, int)
                                      or not 0 < pair_capacity < 2 ** 24):
        # below 2^24: the pair kernel's float row division is exact up to there (binning.py)
        raise ValueError(f"pair_capacity must be None or an int in [1, 2^24), got "
                         f"{pair_capacity!r}")
    if check:
        num_images, g, d = check_inputs(extrinsics, intrinsics, near, far, image_shape,
                                        background_color, means, covariances, sh_coefficients,
                                        opacities)
    else:
        num_images, g, d = means.shape[0], means.shape[1], sh_coefficients.shape[3]
    mod = module_of(means.array)
    Float, UInt32, TensorXf = mod.Float, mod.UInt32, mod.TensorXf
    height, width = image_shape
    is_cuda = dr.backend_v(means.array) == dr.JitBackend.CUDA
    tile_size = settings.resolved_tile_size(is_cuda)
    n_pix = num_images * height * width

    bg = dr.detach(background_color.array)
    background = [dr.gather(Float, bg, dr.arange(UInt32, num_images) * 3 + c) for c in range(3)]
    n = num_images * g
    if n == 0:
        # No Gaussians: every pixel shows the background (nothing to differentiate).
        bg_flat = dr.ravel(mod.Array3f(background))  # [B * 3], (image, channel) order
        image_channel = dr.arange(UInt32, 3 * n_pix) // dr.opaque(UInt32, height * width)
        return RenderOutputDr(
            color=TensorXf(dr.gather(Float, bg_flat, image_channel),
                           shape=(num_images, 3, height, width)),
            alpha=TensorXf(dr.zeros(Float, n_pix), shape=(num_images, height, width)),
            depth=TensorXf(dr.zeros(Float, n_pix), shape=(num_images, height, width)),
            aux={"num_pairs": 0, "tile_size": tile_size, "radii": dr.zeros(Float, 0)})

    # ---- Inputs, one lane per Gaussian ----
    lane = dr.arange(UInt32, n)
    batch = lane // dr.maximum(dr.opaque(UInt32, g), 1)
    # The adjoint of a gather is a scatter-add into the input's gradient. Each input element is
    # read by at most one lane here, so ReduceMode.Permute makes that adjoint a plain scatter
    # (docs/rasteriser_notes.md, "Input gathers"): Local reduced and added atomically lane by
    # lane, and the default (Expand on LLVM) bakes the target size into the kernel and
    # recompiles it for every new number of Gaussians ("Recompilation"). A Permute adjoint
    # *writes* into the source's gradient, which would drop gradients reaching the same input
    # from elsewhere (a loss term on the means, say): the gathers read a private node (x * 1)
    # whose gradient only they write, and whose own adjoint adds into the input's gradient.
    def take(source, index):
        return dr.gather(Float, source, index, mode=dr.ReduceMode.Permute)

    means_a, covs_a, sh_a, opac_a = (t.array * 1.0 for t in (means, covariances,
                                                              sh_coefficients, opacities))
    xyz = [take(means_a, lane * 3 + i) for i in range(3)]
    cov6 = [take(covs_a, lane * 9 + i) for i in (0, 1, 2, 4, 5, 8)]
    coeffs = [[take(sh_a, lane * (3 * d) + (c * d + i))
               for i in range(min(d, 16))] for c in range(3)]
    opac = take(opac_a, lane)
    cam = _gather_camera(_cameras(mod, extrinsics, intrinsics, near, width, height,
                                  settings.projection), batch)

    # ---- Projection, colour and tile rectangles ----
    proj = project(xyz, cov6, opac, coeffs, cam, min(sh_degree_for(d), 3), settings.sh_basis)
    # Evaluate the per-Gaussian stage once: its lazy outputs are read by several later kernels,
    # each of which would otherwise recompute the projection. In a kernel of its own, not fused
    # with tile_rects: CUDA's compiler contracts the projection's arithmetic differently inside
    # differently shaped kernels, and with opacity culling fused in the images differed from
    # the unculled ones by 1 ulp on ~30 % of pixels (H200); apart, they are bit-identical.
    dr.eval(proj.u, proj.v, proj.conic, proj.cov2d, proj.opacity, proj.rgb, proj.z, proj.radius,
            proj.valid)
    grid_x = -(-width // tile_size)
    grid_y = -(-height // tile_size)
    gx_f, gy_f = dr.opaque(Float, float(grid_x)), dr.opaque(Float, float(grid_y))
    x0, x1, y0, y1, count, q_max = tile_rects(proj, tile_size, settings.opacity_cull,
                                              cam.width, cam.height, gx_f, gy_f)
    dr.eval(x0, x1, y0, y1, count, q_max)
    tiles_per_image = grid_x * grid_y
    bins = bin_gaussians(proj, x0, x1, y0, y1, count, q_max, tile_size,
                         batch * dr.opaque(UInt32, tiles_per_image),
                         dr.opaque(UInt32, grid_x), num_images * tiles_per_image,
                         capacity=pair_capacity)

    # ---- Compositing (custom backward) ----
    lanes = pixel_lanes(mod, num_images, height, width, tile_size)
    color, alpha, depth = dr.custom(
        Composite, proj.u, proj.v, *proj.conic, proj.opacity, *proj.rgb, proj.z, bins, lanes,
        background, n_pix, settings.clamp_gradient,
        settings.resolved_backward_scatter(is_cuda))
    return RenderOutputDr(
        color=TensorXf(color, shape=(num_images, 3, height, width)),
        alpha=TensorXf(alpha, shape=(num_images, height, width)),
        depth=TensorXf(depth, shape=(num_images, height, width)),
        aux={"num_pairs": bins.num_pairs, "tile_size": tile_size,
             "radii": dr.select(proj.valid, proj.radius, 0.0), "overflow": bins.overflow,
             "pairs_needed": bins.needed, "pairs_kept": bins.kept})

