"""Rendering scene descriptions with Mitsuba 3: colour, exact depth and per-pixel materials.

Colour: Mitsuba's ``direct`` integrator (emitter and BSDF sampling, no interreflection, so
the noise is low at modest sample counts; the view-dependent appearance names ``path`` in its
description, so that shiny surfaces reflect the scene), box pixel filter, linear radiance
converted to sRGB and rounded to uint8. Depth: one ray per pixel centre, built from *our*
intrinsics and OpenCV extrinsics (not from Mitsuba's sensor), intersected with the Mitsuba
scene; camera-space z, ``+inf`` where the ray misses. The colour image comes from Mitsuba's
sensor; the tests pin that both agree (``tests/data/test_conventions.py``).
"""

import functools
import io
import json
import math

import numpy as np
from PIL import Image

from usplat_dr.data.synth.scenes import terrain_grid
from usplat_dr.data.synth.textures import make_environment, make_texture
from usplat_dr.geometry.cameras import opencv_c2w_to_mitsuba, pixel_directions
from usplat_dr.io.user_files import open_image, rgb8

# Material classes in the per-pixel material map.
MISS, TEXTURED, PLAIN, GLOSSY, CONDUCTOR = 0, 1, 2, 3, 4
MATERIAL_CODES = {"textured": TEXTURED, "plain": PLAIN, "glossy": GLOSSY,
                  "conductor": CONDUCTOR}
#: The two families the metrics and the meter separate: surfaces whose appearance changes with
#: the viewpoint (glossy, metal) and those whose appearance does not (textured, plain).
SHINY, MATTE = (GLOSSY, CONDUCTOR), (TEXTURED, PLAIN)

#: The gains auto exposure may apply (``camera_effects``): a camera's ISO range, in effect.
AUTO_EXPOSURE = (1 / 8, 32.0)

_VARIANTS = {"llvm": "llvm_ad_rgb", "cuda": "cuda_ad_rgb"}


def set_variant(backend: str = "llvm"):
    """Select Mitsuba's variant for ``backend`` ('llvm' or 'cuda') and return the module."""
    import mitsuba as mi  # on first use, not at import (start-up time)

    import usplat_dr  # noqa: F401  (libLLVM before Mitsuba loads Dr.Jit)

    if backend not in _VARIANTS:
        raise ValueError(f"backend must be 'llvm' or 'cuda', got {backend!r}")
    if backend == "llvm":
        from usplat_dr.backend import require_llvm  # loads drjit: not at import (start-up)

        require_llvm()
    if mi.variant() != _VARIANTS[backend]:
        mi.set_variant(_VARIANTS[backend])
    return mi


def intrinsics_for(fov_x_deg: float, resolution: tuple[int, int]) -> np.ndarray:
    """Normalised intrinsics of a pinhole with square pixels and a centred principal point."""
    h, w = resolution
    fx = 0.5 / math.tan(math.radians(fov_x_deg) / 2)
    return np.array([[fx, 0, 0.5], [0, fx * w / h, 0.5], [0, 0, 1]])


@functools.lru_cache(maxsize=64)
def _texture_image(spec_json: str) -> np.ndarray:
    """``make_texture`` of a texture spec (as sorted JSON), built once for the colour and the
    bump map of a surface (a photographic texture's crop and resize cost milliseconds)."""
    image = make_texture(json.loads(spec_json))
    image.flags.writeable = False
    return image


def _bitmap(mi, image: np.ndarray, material: dict, **extra) -> dict:
    s = material.get("uv_scale", 1.0)
    # (a copy: Mitsuba's Bitmap takes writable arrays only, and the cached image is read-only)
    return {"type": "bitmap", "bitmap": mi.Bitmap(np.array(image)), "filter_type": "bilinear",
            "wrap_mode": "repeat", "to_uv": mi.ScalarTransform4f().scale([s, s, 1]), **extra}


def _texture(mi, material: dict) -> dict:
    image = _texture_image(json.dumps(material["texture"], sort_keys=True))
    if "albedo" in material:  # scaled in linear RGB (a float32 bitmap is linear to Mitsuba)
        image = (srgb_to_linear(image.astype(np.float32) / 255.0)
                 * material["albedo"]).astype(np.float32)
    return _bitmap(mi, image, material)


def _bsdf(mi, material: dict) -> dict:
    inner = _bsdf_unbumped(mi, material)
    if not material.get("bump"):
        return inner
    # relief from the texture's own luminance (a bump map shades; the geometry, and so the
    # depth, stay exact)
    image = _texture_image(json.dumps(material["texture"], sort_keys=True))
    lum = image.astype(np.float32).mean(-1, keepdims=True) / 255.0
    return {"type": "bumpmap", "scale": material["bump"], "bsdf": inner,
            "arg": _bitmap(mi, lum, material, raw=True)}


def _bsdf_unbumped(mi, material: dict) -> dict:
    if material["type"] == "plain":
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": material["rgb"]}}
    if material["type"] == "glossy":
        d = {"type": "roughplastic", "distribution": "ggx", "alpha": material["roughness"],
             "diffuse_reflectance": (_texture(mi, material) if "texture" in material else
                                     {"type": "rgb", "value": material["rgb"]})}
        if "ior" in material:
            d["int_ior"] = material["ior"]
        return d
    if material["type"] == "conductor":  # a perfect conductor, tinted: a rough metal
        return {"type": "roughconductor", "material": "none", "distribution": "ggx",
                "alpha": material["roughness"],
                "specular_reflectance": {"type": "rgb", "value": material["rgb"]}}
    if material["type"] == "textured":
        return {"type": "diffuse", "reflectance": _texture(mi, material)}
    raise ValueError(f"unknown material type {material['type']!r}")


def _terrain_mesh(mi, shape: dict):
    t = shape["terrain"]
    grid = terrain_grid(t)
    n, size = t["resolution"], t["size"]
    x = np.linspace(-size / 2, size / 2, n)
    xx, zz = np.meshgrid(x, x)
    verts = np.stack([xx, grid, zz], -1).reshape(-1, 3).astype(np.float32)
    uv = np.stack(np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n)), -1).reshape(-1, 2)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    v00 = (i * n + j).ravel()
    # Counter-clockwise seen from above (+Y), so normals point up.
    faces = np.concatenate([np.stack([v00, v00 + n, v00 + 1], -1),
                            np.stack([v00 + 1, v00 + n, v00 + n + 1], -1)]).astype(np.uint32)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(_bsdf(mi, shape["material"]))
    mesh = mi.Mesh(shape["name"], len(verts), len(faces), props=props, has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(verts.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params["vertex_texcoords"] = mi.Float(uv.astype(np.float32).ravel())
    params.update()
    return mesh


def mitsuba_dict(spec: dict, resolution: tuple[int, int], spp: int, backend: str = "llvm"
                 ) -> dict:
    """The Mitsuba scene dict of a description, with one perspective sensor per camera."""
    mi = set_variant(backend)
    h, w = resolution
    d: dict = {"type": "scene", "integrator": spec.get("integrator") or {
        "type": "direct", "emitter_samples": 1, "bsdf_samples": 1}}
    for s in spec["shapes"]:
        if s["type"] == "terrain":
            d[s["name"]] = _terrain_mesh(mi, s)
            continue
        d[s["name"]] = {"type": s["type"], "to_world": mi.ScalarTransform4f(s["to_world"]),
                        "bsdf": _bsdf(mi, s["material"])}
        if s["type"] in ("rectangle", "disk"):
            # Walls and floors are seen from one side only, but a two-sided BSDF keeps a
            # camera that strays behind one from seeing black.
            d[s["name"]]["bsdf"] = {"type": "twosided", "bsdf": d[s["name"]]["bsdf"]}
    for i, light in enumerate(spec["lights"]):
        if light["type"] == "area":
            # A disk, not a rectangle: Mitsuba keeps analytic shapes in the dict's order but
            # meshes (rectangles included) in an order that changes from run to run, and the
            # direct integrator picks an emitter by its index, so rectangle lamps would make
            # the noise (and the bytes written) differ between runs.
            d[f"light{i}"] = {"type": "disk",
                              "to_world": mi.ScalarTransform4f(light["to_world"]),
                              "emitter": {"type": "area", "radiance": {
                                  "type": "rgb", "value": light["radiance"]}}}
        elif light["type"] == "point":
            d[f"light{i}"] = {"type": "point", "position": light["position"],
                              "intensity": {"type": "rgb", "value": light["intensity"]}}
        elif light["type"] == "directional":
            d[f"light{i}"] = {"type": "directional", "direction": light["direction"],
                              "irradiance": {"type": "rgb", "value": light["irradiance"]}}
        elif light["type"] == "envmap":
            sky = make_environment({**light, "version": spec.get("version", 1)})
            d[f"light{i}"] = {"type": "envmap", "scale": light["scale"], "bitmap": mi.Bitmap(sky)}
        elif light["type"] == "constant":
            d[f"light{i}"] = {"type": "constant", "radiance": {"type": "rgb",
                                                               "value": light["radiance"]}}
        else:
            raise ValueError(f"unknown light type {light['type']!r}")
    fov = spec["cameras"]["fov_x_deg"]
    near, far = spec["near_far"]
    for i, c2w in enumerate(spec["cameras"]["c2w"]):
        d[f"sensor{i:04d}"] = {
            "type": "perspective", "fov": fov, "fov_axis": "x",
            "near_clip": near * 0.1, "far_clip": far * 100.0,
            "to_world": mi.ScalarTransform4f(opencv_c2w_to_mitsuba(np.asarray(c2w)).tolist()),
            "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"},
                     "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": spp},
        }
    return d


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) on linear values clipped to [0, 1]."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def srgb8(x: np.ndarray) -> np.ndarray:
    """uint8 sRGB of linear values (``linear_to_srgb``, rounded)."""
    return (linear_to_srgb(x) * 255 + 0.5).astype(np.uint8)


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """The inverse of ``linear_to_srgb`` (IEC 61966-2-1) on sRGB values in [0, 1]."""
    return np.where(c <= 0.04045, c / 12.92, np.power((c + 0.055) / 1.055, 2.4))


def trace_depth(mi, scene, c2w: np.ndarray, intrinsics: np.ndarray,
                resolution: tuple[int, int], shape_codes: dict[str, int] | None = None):
    """Camera-space z at every pixel centre (``+inf`` on a miss) and, with ``shape_codes``
    (shape id -> material code), the material code of the surface seen there."""
    import drjit as dr  # loaded with Mitsuba, not at import (start-up time)

    h, w = resolution
    d_cam = pixel_directions(intrinsics, resolution).reshape(-1, 3)
    norm = np.linalg.norm(d_cam, axis=-1)
    d_world = (d_cam / norm[:, None]) @ np.asarray(c2w)[:3, :3].T
    o = np.broadcast_to(np.asarray(c2w)[:3, 3], d_world.shape)
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, k].astype(np.float32)) for k in range(3)]),
                   mi.Vector3f(*[mi.Float(d_world[:, k].astype(np.float32)) for k in range(3)]))
    si = scene.ray_intersect(ray)
    t = np.array(dr.select(si.is_valid(), si.t, dr.inf), dtype=np.float64)
    # t is the distance along the unit ray; z = t * cos(angle to the optical axis) = t / |d_cam|.
    depth = (t / norm).reshape(h, w)
    codes = None
    if shape_codes is not None:
        # Shape pointers compare as registry ids: map each id seen to its material code.
        ids = np.array(dr.reinterpret_array(mi.UInt32, si.shape))
        all_ids = np.array(dr.reinterpret_array(mi.UInt32, scene.shapes_dr()))
        lut = {int(k): shape_codes.get(s.id(), MISS) for k, s in zip(all_ids, scene.shapes())}
        uniq, inverse = np.unique(ids, return_inverse=True)
        codes = np.array([lut.get(int(k), MISS) for k in uniq], dtype=np.uint8)[inverse]
        codes = np.where(np.isfinite(t), codes, MISS).reshape(h, w).astype(np.uint8)
    return depth, codes


def camera_effects(linear: np.ndarray, effects: dict, frame: int) -> np.ndarray:
    """A photograph of linear radiance [H, W, 3] as a camera would take it: uint8 sRGB after,
    in this order, auto exposure (the frame scaled so that the geometric mean of its luminance
    is ``key``, by a gain in ``AUTO_EXPOSURE``; NaN or infinite path-tracer samples as 0),
    defocus (a Gaussian of ``defocus`` x width standard deviation), motion blur
    (a line of up to ``motion`` x width pixels, its length and direction drawn per frame),
    vignetting (1 - ``vignetting`` r^2, r = 1 at the corners), exposure (2^N(0,
    ``exposure_sd_ev``)) and white balance (per channel e^N(0, ``white_balance_sd``), green
    fixed) drawn per frame, sensor noise (Gaussian, standard deviation ``noise`` x sqrt(x +
    0.01): shot noise with a read-noise floor), sRGB, then a JPEG round trip at
    ``jpeg_quality``. Deterministic for (``effects["seed"]``, ``frame``).

    Examples:
        >>> fx = {"seed": 0, "key": 0.18, "defocus": 0.01, "motion": 0.01, "vignetting": 0.3,
        ...       "exposure_sd_ev": 0.15, "white_balance_sd": 0.04, "noise": 0.01,
        ...       "jpeg_quality": 90}
        >>> a = camera_effects(np.full((16, 16, 3), 0.2), fx, 3)
        >>> a.dtype, a.shape, bool((a == camera_effects(np.full((16, 16, 3), 0.2), fx, 3)).all())
        (dtype('uint8'), (16, 16, 3), True)
    """
    from scipy import ndimage  # on first use (start-up time); scikit-image needs SciPy

    rng = np.random.default_rng([effects["seed"], frame])
    h, w = linear.shape[:2]
    x = np.nan_to_num(np.asarray(linear, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    luminance = np.clip(x, 0.0, None) @ np.array([0.2126, 0.7152, 0.0722])
    key = float(np.exp(np.log(luminance + 1e-4).mean()))
    x = x * float(np.clip(effects["key"] / key, *AUTO_EXPOSURE))
    sigma = effects["defocus"] * w
    if sigma > 0.05:
        x = ndimage.gaussian_filter(x, (sigma, sigma, 0), mode="nearest")
    length = effects["motion"] * w * rng.random()
    angle = rng.uniform(0, np.pi)
    if length >= 0.5:  # a line kernel, antialiased by sampling it finely
        size = 2 * int(np.ceil(length / 2)) + 1
        kernel = np.zeros((size, size))
        for t in np.linspace(-length / 2, length / 2, 8 * size):
            kernel[round(size // 2 + t * np.sin(angle)),
                   round(size // 2 + t * np.cos(angle))] += 1.0
        kernel /= kernel.sum()
        x = np.stack([ndimage.convolve(x[..., c], kernel, mode="nearest") for c in range(3)],
                     -1)
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx + 0.5 - w / 2) ** 2 + (yy + 0.5 - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    x = x * (1.0 - effects["vignetting"] * r2)[..., None]
    gain = 2.0 ** rng.normal(0.0, effects["exposure_sd_ev"])
    balance = np.exp(rng.normal(0.0, effects["white_balance_sd"], 3))
    balance[1] = 1.0
    x = np.clip(x * gain * balance, 0.0, None)
    x = x + rng.normal(0.0, 1.0, x.shape) * effects["noise"] * np.sqrt(x + 0.01)
    buffer = io.BytesIO()
    Image.fromarray(srgb8(x)).save(buffer, format="JPEG", quality=int(effects["jpeg_quality"]))
    return rgb8(open_image(buffer.getvalue(), "a JPEG round trip"))


def render_spec(spec: dict, resolution: tuple[int, int], spp: int = 64, seed: int = 0,
                backend: str = "llvm", frames: list[int] | None = None):
    """Render a scene description: uint8 sRGB images [V, H, W, 3], float32 depths [V, H, W]
    (camera-space z, +inf on a miss), uint8 material maps [V, H, W] (``MISS``, ``TEXTURED``,
    ``PLAIN``, ``GLOSSY``, ``CONDUCTOR``) and normalised intrinsics [3, 3]."""
    mi = set_variant(backend)
    scene = mi.load_dict(mitsuba_dict(spec, resolution, spp, backend))
    sensors = scene.sensors()
    intr = intrinsics_for(spec["cameras"]["fov_x_deg"], resolution)
    codes = {s["name"]: MATERIAL_CODES[s["material"]["type"]] for s in spec["shapes"]}
    frames = range(len(sensors)) if frames is None else frames
    images, depths, materials = [], [], []
    for i in frames:
        pass_seed = (seed * 100_003 + i) % 2**31  # Mitsuba seeds are 32-bit
        img = np.array(mi.render(scene, sensor=sensors[i], seed=pass_seed, spp=spp))
        if "camera_effects" in spec:  # the photographic appearance
            images.append(camera_effects(img[..., :3], spec["camera_effects"], i))
        else:
            images.append(srgb8(img[..., :3]))
        depth, mat = trace_depth(mi, scene, np.asarray(spec["cameras"]["c2w"][i]), intr,
                                 resolution, codes)
        depths.append(depth.astype(np.float32))
        materials.append(mat)
    return np.stack(images), np.stack(depths), np.stack(materials), intr
