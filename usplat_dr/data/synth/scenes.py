"""Procedural scene descriptions with known geometry (numpy and torch; Mitsuba builds them later).

A description ("spec") is a JSON-able dict, stored with every synthetic scene so it can be
re-rendered at another resolution (``usplat_dr.data.synth.render.render_spec``)::

    {"version": 1 | 2, "kind": "indoor" | "outdoor" | "object", "seed": int,
     "shapes": [{"name", "type": rectangle|cube|cylinder|sphere|disk|terrain,
                 "to_world": 4x4, "material": {...}, ...}],
     "lights": [{"type": area|point|directional|constant, ...}],
     "cameras": {"c2w": [V x 4x4, OpenCV], "fov_x_deg": float},
     "near_far": [near, far], "tags": [...]}

World: +Y up, metres. Cameras: OpenCV camera-to-world (see ``usplat_dr.geometry.cameras``).
Materials: ``{"type": "textured", "texture": spec, "uv_scale": s}`` (diffuse, procedural
texture), ``{"type": "plain", "rgb": [...]}`` (textureless diffuse), ``{"type": "glossy",
"rgb": [...], "roughness": a}`` (rough plastic: view-dependent highlights; optionally a
``texture``, ``uv_scale`` and ``albedo`` (its scale) instead of ``rgb``, and an ``ior``) or
``{"type": "conductor",
"rgb": [...], "roughness": a}`` (a tinted rough metal: it shows what surrounds it).

Appearance (``make_spec(..., appearance=)``): ``"diffuse"`` (the default: the scenes above,
Mitsuba's ``direct`` integrator under a constant sky) or ``"view-dependent"``: the same
geometry and cameras (the same seed), with at least half of the surfaces glossy or metallic
(floors, terrain and turntables always), a structured environment map instead of the constant
sky, and Mitsuba's ``path`` integrator (``max_depth`` 3), so that shiny surfaces reflect the
scene and the sky. Its description has ``"appearance"``, ``"integrator"`` and an ``envmap``
light; tags gain ``view_dependent``. ``"rough-glossy"``: the view-dependent appearance with the
same surfaces, sky and lamps (the same random stream) but rough shiny materials (GGX roughness
0.15-0.4, ``ROUGH_ROUGHNESS``): broad highlights of the sky's panels, sun and lamps (to such a
surface a few large lights) that move smoothly with the viewpoint, which colour of spherical
harmonics degree 2 can hold and two context views both see; tags gain ``view_dependent`` and
``rough``.

``"photographic"``: the same rooms, terrains and turntables made to look like photographs
(``photographic``): most surfaces carry photographic textures (``textures.PHOTOS``) with bump
relief from their own luminance, some rough-glossy; clutter of many small textured objects
on the ground; the structured sky with a sun as an environment light, larger lamps (soft
shadows) and a path tracer (``max_depth`` 4: interreflection); focal lengths of 24-70 mm
equivalent and hand-held jitter on every camera; and camera effects applied to the linear
render (``camera_effects``: defocus and motion blur, vignetting, exposure and white balance
changing between frames, sensor noise, JPEG). Depth stays exact: bump maps shade and blur
blurs the image only; the clutter is geometry, traced like the rest. Tags gain
``photographic``.
"""

import math

import numpy as np
import torch

from usplat_dr.data.synth.textures import photo_texture_spec, random_texture_spec
from usplat_dr.geometry.cameras import look_at

KINDS = ("indoor", "outdoor", "object")
APPEARANCES = ("diffuse", "view-dependent", "rough-glossy", "photographic")
SPEC_VERSION = 1
#: Shapes that are always shiny in the view-dependent appearance (the ground of each kind).
GROUND = ("floor", "terrain", "turntable")


# ---- Transforms (4x4, column vectors) ----


def translate(v) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = v
    return m


def scale(v) -> np.ndarray:
    return np.diag([*np.broadcast_to(np.asarray(v, dtype=float), (3,)), 1.0])


def rotate(axis, degrees) -> np.ndarray:
    """Rotation by ``degrees`` about ``axis`` (right-handed, Rodrigues)."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    t = math.radians(degrees)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * (k @ k)
    return m


def look_at_np(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """OpenCV camera-to-world looking from ``eye`` at ``target`` (``geometry.cameras.look_at``
    on numpy arrays, float64)."""
    eye, target, up = (torch.tensor(np.asarray(v, dtype=np.float64)) for v in (eye, target, up))
    return look_at(eye, target, up).numpy()


def _mat(rng: np.random.Generator, p_plain: float, p_glossy: float) -> dict:
    u = rng.random()
    rgb = (0.2 + 0.7 * rng.random(3)).round(3).tolist()
    if u < p_plain:
        return {"type": "plain", "rgb": rgb}
    if u < p_plain + p_glossy:
        return {"type": "glossy", "rgb": rgb, "roughness": round(float(rng.uniform(0.05, 0.15)), 3)}
    return {"type": "textured", "texture": random_texture_spec(rng),
            "uv_scale": round(float(rng.uniform(1, 3)), 2)}


def _shape(name: str, typ: str, to_world: np.ndarray, material: dict, **extra) -> dict:
    return {"name": name, "type": typ, "to_world": np.round(to_world, 6).tolist(),
            "material": material, **extra}


def _box(name, center, half, material, yaw=0.0) -> dict:
    return _shape(name, "cube", translate(center) @ rotate([0, 1, 0], yaw) @ scale(half), material)


def _pole(name, base, height, radius, material) -> dict:
    # Mitsuba's cylinder runs from z=0 to z=1; rotate its axis onto +Y.
    m = translate(base) @ rotate([1, 0, 0], -90) @ scale([radius, radius, height])
    return _shape(name, "cylinder", m, material)


def _sphere(name, center, radius, material) -> dict:
    return _shape(name, "sphere", translate(center) @ scale(radius), material)


# ---- Camera paths ----


def walkthrough(rng: np.random.Generator, frames: int, start, heading_deg, length,
                height_fn=None, eye=1.6) -> list[np.ndarray]:
    """A handheld-video-like path: forward motion with a sideways sway, small yaw and pitch
    oscillations (a few degrees), as in RealEstate10K walkthroughs."""
    start = np.asarray(start, dtype=float)
    h = math.radians(heading_deg)
    fwd, side = np.array([math.sin(h), 0, math.cos(h)]), np.array([math.cos(h), 0, -math.sin(h)])
    sway, w_sway, ph = rng.uniform(0.1, 0.35), rng.uniform(0.5, 1.5), rng.uniform(0, 2 * math.pi)
    yaw_amp, w_yaw, ph_yaw = rng.uniform(4, 12), rng.uniform(0.5, 1.5), rng.uniform(0, 2 * math.pi)
    pitch0, pitch_amp = rng.uniform(-8, 2), rng.uniform(1, 4)
    cams = []
    for i in range(frames):
        t = i / max(frames - 1, 1)
        p = start + fwd * length * t + side * sway * math.sin(2 * math.pi * w_sway * t + ph)
        y = eye + (height_fn(p[0], p[2]) if height_fn else 0.0)
        pos = np.array([p[0], y, p[2]])
        yaw = h + math.radians(yaw_amp * math.sin(2 * math.pi * w_yaw * t + ph_yaw))
        pitch = math.radians(pitch0 + pitch_amp * math.sin(2 * math.pi * t + ph))
        d = np.array([math.sin(yaw) * math.cos(pitch), math.sin(pitch),
                      math.cos(yaw) * math.cos(pitch)])
        cams.append(look_at_np(pos, pos + d))
    return cams


def orbit(frames: int, center, radius, elevation_deg, start_deg, arc_deg) -> list[np.ndarray]:
    """Cameras on a horizontal arc around ``center``, looking at it (turntable capture)."""
    center = np.asarray(center, dtype=float)
    cams = []
    for i in range(frames):
        a = math.radians(start_deg + arc_deg * i / max(frames - 1, 1))
        e = math.radians(elevation_deg)
        eye = center + radius * np.array([math.cos(e) * math.sin(a), math.sin(e),
                                          math.cos(e) * math.cos(a)])
        cams.append(look_at_np(eye, center))
    return cams


# ---- Scene kinds ----


def indoor_room(rng: np.random.Generator, frames: int) -> dict:
    """A room: floor, ceiling, four walls, furniture-like boxes, thin poles, area lights; a
    walkthrough camera path."""
    sx, sz, h = rng.uniform(5, 8), rng.uniform(5, 8), rng.uniform(2.7, 3.2)
    textureless_walls = rng.random() < 0.35
    wall_mat = ({"type": "plain", "rgb": (0.6 + 0.3 * rng.random(3)).round(3).tolist()}
                if textureless_walls else _mat(rng, 0.0, 0.0))
    floor_mat = _mat(rng, 0.0, 0.0)
    shapes = [
        _shape("floor", "rectangle", translate([0, 0, 0]) @ rotate([1, 0, 0], -90)
               @ scale([sx / 2, sz / 2, 1]), floor_mat),
        _shape("ceiling", "rectangle", translate([0, h, 0]) @ rotate([1, 0, 0], 90)
               @ scale([sx / 2, sz / 2, 1]), _mat(rng, 0.5, 0.0)),
    ]
    for i, (pos, yaw, half_w) in enumerate([((0, h / 2, -sz / 2), 0, sx / 2),
                                            ((0, h / 2, sz / 2), 180, sx / 2),
                                            ((-sx / 2, h / 2, 0), 90, sz / 2),
                                            ((sx / 2, h / 2, 0), -90, sz / 2)]):
        shapes.append(_shape(f"wall{i}", "rectangle", translate(pos) @ rotate([0, 1, 0], yaw)
                             @ scale([half_w, h / 2, 1]), wall_mat))

    # Camera path first, then furniture placed off it.
    heading = rng.uniform(0, 360)
    length = rng.uniform(1.5, 3.0)
    hd = math.radians(heading)
    start = -0.5 * length * np.array([math.sin(hd), 0, math.cos(hd)])
    start += rng.uniform(-0.5, 0.5, 3) * [1, 0, 1]
    cams = walkthrough(rng, frames, start, heading, length, eye=rng.uniform(1.3, 1.7))
    path = np.array([c[:3, 3] for c in cams])

    glossy = rng.random() < 0.5
    n_boxes, placed = int(rng.integers(4, 8)), 0
    for _ in range(60):
        if placed == n_boxes:
            break
        half = rng.uniform([0.2, 0.2, 0.2], [0.8, 0.6, 0.8]) * (1.4 if placed == 0 else 1.0)
        c = np.array([rng.uniform(-sx / 2 + half[0], sx / 2 - half[0]), half[1],
                      rng.uniform(-sz / 2 + half[2], sz / 2 - half[2])])
        r = max(half[0], half[2]) * 1.42 + 0.5  # bounding circle + clearance for the camera
        if (np.hypot(path[:, 0] - c[0], path[:, 2] - c[2]) < r).any():
            continue
        mat = _mat(rng, 0.2, 0.0)
        if glossy and placed == 0:
            mat = {"type": "glossy", "rgb": (0.2 + 0.6 * rng.random(3)).round(3).tolist(),
                   "roughness": round(float(rng.uniform(0.05, 0.12)), 3)}
        shapes.append(_box(f"box{placed}", c, half, mat, yaw=rng.uniform(-30, 30)))
        if rng.random() < 0.4:  # an object on the box
            shapes.append(_sphere(f"ball{placed}", c + [0, half[1] + 0.15, 0], 0.15,
                                  _mat(rng, 0.2, 0.3)))
        placed += 1
    n_poles = int(rng.integers(2, 4))
    for i in range(n_poles):
        for _ in range(20):
            b = np.array([rng.uniform(-sx / 2 + 0.3, sx / 2 - 0.3), 0,
                          rng.uniform(-sz / 2 + 0.3, sz / 2 - 0.3)])
            if (np.hypot(path[:, 0] - b[0], path[:, 2] - b[2]) > 0.5).all():
                shapes.append(_pole(f"pole{i}", b, h, rng.uniform(0.02, 0.05), _mat(rng, 0.3, 0.2)))
                break
    lights = []
    for i in range(2):
        p = [rng.uniform(-sx / 4, sx / 4), h - 0.01, rng.uniform(-sz / 4, sz / 4)]
        lights.append({"type": "area", "to_world": np.round(
            translate(p) @ rotate([1, 0, 0], 90) @ scale([0.35, 0.35, 1]), 6).tolist(),
            "radiance": round(float(rng.uniform(12, 20)), 2)})
    lights.append({"type": "point", "position": np.round(path.mean(0) + [0, 0.6, 0], 4).tolist(),
                   "intensity": round(float(rng.uniform(1.5, 3)), 2)})
    tags = ["indoor", "walkthrough", "thin"] + (["textureless"] if textureless_walls else [])
    tags += ["glossy"] if glossy else []
    return {"shapes": shapes, "lights": lights, "cameras": cams, "near_far": [0.2, 20.0],
            "tags": tags, "fov_x_deg": float(rng.uniform(60, 75))}


def terrain_height(spec: dict, x, z):
    """Height of the terrain described by ``spec`` at world (x, z) (bilinear in its grid)."""
    grid = terrain_grid(spec)
    n, size = spec["resolution"], spec["size"]
    u = np.clip((np.asarray(x) + size / 2) / size * (n - 1), 0, n - 1.0001)
    v = np.clip((np.asarray(z) + size / 2) / size * (n - 1), 0, n - 1.0001)
    i, j = np.floor(v).astype(int), np.floor(u).astype(int)
    fu, fv = u - j, v - i
    return ((grid[i, j] * (1 - fu) + grid[i, j + 1] * fu) * (1 - fv)
            + (grid[i + 1, j] * (1 - fu) + grid[i + 1, j + 1] * fu) * fv)


def terrain_grid(spec: dict) -> np.ndarray:
    """[n, n] heights (row = z, column = x) of a terrain spec: a few smooth random hills."""
    rng = np.random.default_rng(spec["seed"])
    n, size = spec["resolution"], spec["size"]
    x = np.linspace(-size / 2, size / 2, n)
    xx, zz = np.meshgrid(x, x)
    h = np.zeros_like(xx)
    for _ in range(spec["hills"]):
        c = rng.uniform(-size / 2, size / 2, 2)
        s = rng.uniform(2, 8)
        h += rng.uniform(-1, 1) * spec["amplitude"] * np.exp(-((xx - c[0])**2 + (zz - c[1])**2)
                                                             / (2 * s * s))
    return h


def outdoor_terrain(rng: np.random.Generator, frames: int) -> dict:
    """Hilly textured terrain with objects (boxes, balls, poles and 'trees'), sun and sky; a
    walkthrough path at eye height above the ground."""
    terrain = {"seed": int(rng.integers(2**31)), "resolution": 65, "size": 40.0,
               "hills": 12, "amplitude": float(rng.uniform(0.3, 1.0))}
    shapes = [_shape("terrain", "terrain", np.eye(4), _mat(rng, 0.0, 0.0), terrain=terrain)]
    shapes[0]["material"]["uv_scale"] = 12.0
    heading, length = rng.uniform(0, 360), rng.uniform(3, 6)
    hd = math.radians(heading)
    start = -0.5 * length * np.array([math.sin(hd), 0, math.cos(hd)])

    def ground(x, z):
        return float(terrain_height(terrain, x, z))

    cams = walkthrough(rng, frames, start, heading, length, height_fn=ground, eye=1.6)
    path = np.array([c[:3, 3] for c in cams])
    glossy = rng.random() < 0.5
    n_obj = int(rng.integers(8, 14))
    fwd = np.array([math.sin(hd), 0, math.cos(hd)])
    k = 0
    for _ in range(100):
        if k == n_obj:
            break
        # Mostly in front of the path, within 3-15 m.
        ang = math.radians(rng.uniform(-50, 50))
        d = rng.uniform(3, 15)
        dirv = np.array([fwd[0] * math.cos(ang) - fwd[2] * math.sin(ang), 0,
                         fwd[0] * math.sin(ang) + fwd[2] * math.cos(ang)])
        c = path[rng.integers(len(path))] * [1, 0, 1] + dirv * d
        if (np.hypot(path[:, 0] - c[0], path[:, 2] - c[2]) < 1.5).any():
            continue
        g = ground(c[0], c[2])
        kind = rng.integers(4)
        mat = _mat(rng, 0.15, 0.0)
        if glossy and k == 0:
            mat = {"type": "glossy", "rgb": (0.2 + 0.6 * rng.random(3)).round(3).tolist(),
                   "roughness": 0.08}
            kind = 1
        if kind == 0:
            half = rng.uniform([0.3, 0.3, 0.3], [1.2, 1.0, 1.2])
            shapes.append(_box(f"obj{k}", [c[0], g + half[1] - 0.05, c[2]], half, mat,
                               yaw=rng.uniform(0, 90)))
        elif kind == 1:
            r = rng.uniform(0.3, 0.9)
            shapes.append(_sphere(f"obj{k}", [c[0], g + r - 0.05, c[2]], r, mat))
        elif kind == 2:
            shapes.append(_pole(f"obj{k}", [c[0], g - 0.1, c[2]], rng.uniform(2, 4),
                                rng.uniform(0.03, 0.08), mat))
        else:  # a tree: trunk and crown
            hgt = rng.uniform(1.5, 3)
            shapes.append(_pole(f"obj{k}", [c[0], g - 0.1, c[2]], hgt, 0.12,
                                {"type": "plain", "rgb": [0.35, 0.25, 0.15]}))
            shapes.append(_sphere(f"obj{k}crown", [c[0], g + hgt, c[2]], rng.uniform(0.6, 1.1),
                                  {"type": "textured", "texture": {
                                      **random_texture_spec(rng), "pattern": "noise",
                                      "colors": [[0.1, 0.4, 0.1], [0.25, 0.55, 0.15],
                                                 [0.05, 0.25, 0.05]]}, "uv_scale": 2.0}))
        k += 1
    sun = rng.uniform([-1, -1.0, -1], [1, -0.4, 1])
    lights = [{"type": "directional", "direction": np.round(sun / np.linalg.norm(sun), 4).tolist(),
               "irradiance": round(float(rng.uniform(2.5, 3.5)), 2)},
              {"type": "constant", "radiance": [0.35, 0.45, 0.6]}]
    tags = ["outdoor", "walkthrough", "thin"] + (["glossy"] if glossy else [])
    return {"shapes": shapes, "lights": lights, "cameras": cams, "near_far": [0.5, 100.0],
            "tags": tags, "fov_x_deg": float(rng.uniform(60, 75))}


def object_turntable(rng: np.random.Generator, frames: int) -> dict:
    """Objects on a textured turntable, captured on an orbit (DTU-like near 2.125 / far 4.525)."""
    shapes = [_shape("turntable", "disk", translate([0, 0, 0]) @ rotate([1, 0, 0], -90)
                     @ scale(1.0), _mat(rng, 0.0, 0.0))]
    textureless = rng.random() < 0.35
    glossy = rng.random() < 0.5
    n = int(rng.integers(2, 5))
    for i in range(n):
        c = np.array([rng.uniform(-0.5, 0.5), 0, rng.uniform(-0.5, 0.5)])
        mat = _mat(rng, 0.0, 0.0)
        if textureless and i == 0:
            mat = {"type": "plain", "rgb": (0.3 + 0.6 * rng.random(3)).round(3).tolist()}
        if glossy and i == n - 1:
            mat = {"type": "glossy", "rgb": (0.2 + 0.6 * rng.random(3)).round(3).tolist(),
                   "roughness": round(float(rng.uniform(0.05, 0.12)), 3)}
        if i % 3 == 0:
            r = rng.uniform(0.2, 0.4)
            shapes.append(_sphere(f"obj{i}", c + [0, r, 0], r, mat))
        elif i % 3 == 1:
            half = rng.uniform(0.12, 0.3, 3)
            shapes.append(_box(f"obj{i}", c + [0, half[1], 0], half, mat, yaw=rng.uniform(0, 90)))
        else:
            shapes.append(_pole(f"obj{i}", c, rng.uniform(0.4, 0.8), rng.uniform(0.05, 0.15), mat))
    cams = orbit(frames, [0, 0.3, 0], rng.uniform(3.2, 3.5), rng.uniform(20, 35),
                 rng.uniform(0, 360), rng.uniform(150, 200))
    sun = rng.uniform([-1, -1.0, -1], [1, -0.5, 1])
    lights = [{"type": "directional", "direction": np.round(sun / np.linalg.norm(sun), 4).tolist(),
               "irradiance": 2.5},
              {"type": "constant", "radiance": [0.4, 0.4, 0.42]}]
    tags = ["object", "orbit"] + (["textureless"] if textureless else [])
    tags += ["glossy"] if glossy else []
    return {"shapes": shapes, "lights": lights, "cameras": cams, "near_far": [2.125, 4.525],
            "tags": tags, "fov_x_deg": float(rng.uniform(30, 38))}


BUILDERS = {"indoor": indoor_room, "outdoor": outdoor_terrain, "object": object_turntable}


#: The view-dependent appearance's shiny materials: GGX roughness, clear-coat index of
#: refraction (F0 = ((ior - 1) / (ior + 1))^2), the chance that a non-ground shape is metal,
#: and the albedo of a clear coat's diffuse base relative to the diffuse appearance's (a darker
#: base lets what the coat reflects show). Near-mirror roughness: a sharp reflection moves
#: with the viewpoint, and a path tracer samples it with little noise.
SHINY_ROUGHNESS, SHINY_IOR, METAL_CHANCE, GLOSSY_BASE = (0.01, 0.05), (1.8, 2.6), 0.6, 0.5
#: The view-dependent appearance's integrator depth (camera, shiny surface, what it reflects,
#: a light) and environment map resolution.
VD_MAX_DEPTH, VD_ENV_RES = 3, (64, 128)
#: Indoor lamps grow by this factor (same power) in the view-dependent appearance.
LAMP_SCALE = 3.0
#: The ``version`` of a view-dependent description: 2 for the near-mirror materials above (and
#: ``textures.make_environment``'s softer sun and more panels); 1, as every diffuse one, for
#: its first version (roughness 0.03-0.15 on a full-albedo base under a 32x64 sky, which failed
#: its acceptance). Stored descriptions re-render as they were made.
VD_VERSION = 2
#: The rough-glossy appearance's GGX roughness: a highlight spans tens of degrees (broad view
#: dependence, unlike the near-mirror reflections that the view-dependent appearance's
#: version 2 made and that a feed-forward model did not learn from two views).
ROUGH_ROUGHNESS = (0.15, 0.4)


def _shiny(rng: np.random.Generator, material: dict, metal: bool,
           roughness_range: tuple[float, float] = SHINY_ROUGHNESS) -> dict:
    """A glossy (clear-coated, keeping a texture) or metallic version of ``material``."""
    roughness = round(float(rng.uniform(*roughness_range)), 3)
    if metal:
        tint = (0.55 + 0.4 * rng.random(3)).round(3).tolist()
        return {"type": "conductor", "rgb": tint, "roughness": roughness}
    out = {"type": "glossy", "roughness": roughness,
           "ior": round(float(rng.uniform(*SHINY_IOR)), 3)}
    if material["type"] == "textured":
        out.update(texture=material["texture"], uv_scale=material.get("uv_scale", 1.0),
                   albedo=GLOSSY_BASE)
    else:
        rgb = np.asarray(material.get("rgb", 0.2 + 0.6 * rng.random(3)), dtype=np.float64)
        out["rgb"] = (rgb * GLOSSY_BASE).round(3).tolist()
    return out


def environment_spec(rng: np.random.Generator, strength: float) -> dict:
    """A structured sky (``textures.make_environment``): gradient, sun glow, bright panels."""
    return {"type": "envmap", "seed": int(rng.integers(2**31)), "res": list(VD_ENV_RES),
            "scale": round(float(strength), 3)}


def view_dependent(spec: dict, rng: np.random.Generator, appearance: str = "view-dependent"
                   ) -> dict:
    """The view-dependent (or rough-glossy) appearance of a description (module docstring):
    shapes and cameras unchanged, materials, sky and integrator replaced."""
    rough = appearance == "rough-glossy"
    shapes = [dict(s) for s in spec["shapes"]]
    n = len(shapes)
    ground = [i for i, s in enumerate(shapes) if s["name"] in GROUND]
    others = [i for i in range(n) if i not in ground]
    rng.shuffle(others)
    # at least half of the surfaces, the ground always; the rest at random (70 %)
    need = max(0, -(-n // 2) - len(ground))
    chosen = set(ground) | set(others[:need]) | {i for i in others[need:] if rng.random() < 0.7}
    for i in sorted(chosen):
        metal = shapes[i]["name"] not in GROUND and rng.random() < METAL_CHANCE
        shapes[i]["material"] = _shiny(rng, shapes[i]["material"], metal,
                                       ROUGH_ROUGHNESS if rough else SHINY_ROUGHNESS)
    lights = []
    for light in spec["lights"]:
        if light["type"] == "constant":  # the constant sky becomes a structured one
            lights.append(environment_spec(rng, 1.3 * float(np.mean(light["radiance"]))))
        elif light["type"] == "area":
            # Three times the size at a ninth of the radiance (the same power): small bright
            # lamps reached through a near-mirror bounce off a diffuse surface (caustic paths)
            # are what makes a path tracer's fireflies.
            to_world = np.asarray(light["to_world"]) @ scale([LAMP_SCALE, LAMP_SCALE, 1.0])
            lights.append({**light, "to_world": np.round(to_world, 6).tolist(),
                           "radiance": round(light["radiance"] / LAMP_SCALE**2, 3)})
        else:
            lights.append(light)
    return {**spec, "version": VD_VERSION, "shapes": shapes, "lights": lights,
            "appearance": appearance,
            "integrator": {"type": "path", "max_depth": VD_MAX_DEPTH},
            "tags": [*spec["tags"], "view_dependent", *(["rough"] if rough else [])]}


#: The photographic appearance: the chance that a surface is photo-textured diffuse,
#: photo-textured rough-glossy, or keeps its procedural material (the rest: plain); the bump
#: scale range; the glossy roughness; the path tracer's depth; focal lengths (mm, 36 mm film).
PHOTO_DIFFUSE, PHOTO_GLOSSY, PHOTO_KEEP = 0.7, 0.12, 0.1
PHOTO_BUMP, PHOTO_ROUGHNESS, PHOTO_MAX_DEPTH, PHOTO_FOCAL_MM = (0.3, 2.0), (0.2, 0.45), 4, (24, 70)
#: The texture repeat of a surface that had none (a plain wall, a box).
PHOTO_UV = 2.0
#: Clutter per kind: (count range, size range in metres, clearance from the camera path).
CLUTTER = {"indoor": ((10, 26), (0.04, 0.22), 0.45), "outdoor": ((15, 35), (0.08, 0.5), 1.2),
           "object": ((5, 13), (0.03, 0.12), 0.0)}
#: The auto exposure's target: the geometric mean of a frame's linear luminance (middle grey).
PHOTO_KEY = 0.18
#: The ``version`` of a photographic description (3: its first).
PHOTO_VERSION = 3


def _photo_material(rng: np.random.Generator, material: dict) -> dict:
    """A photographic version of ``material`` (``PHOTO_*``)."""
    u = rng.random()
    tex = photo_texture_spec(rng)
    # the repeat of the surface's own texture (a terrain's is large), jittered: a photograph
    # keeps its detail on large surfaces
    uv = round(float(material.get("uv_scale", PHOTO_UV) * rng.uniform(0.6, 1.6)), 2)
    bump = round(float(rng.uniform(*PHOTO_BUMP)), 3) if rng.random() < 0.6 else 0.0
    if u < PHOTO_DIFFUSE:
        return {"type": "textured", "texture": tex, "uv_scale": uv, "bump": bump}
    if u < PHOTO_DIFFUSE + PHOTO_GLOSSY:  # no bump: a bumped rough plastic gave NaN pixels
        return {"type": "glossy", "texture": tex, "uv_scale": uv, "albedo": 0.8,
                "roughness": round(float(rng.uniform(*PHOTO_ROUGHNESS)), 3), "ior": 1.5}
    if u < PHOTO_DIFFUSE + PHOTO_GLOSSY + PHOTO_KEEP or material["type"] == "conductor":
        return material
    return {"type": "plain", "rgb": (0.15 + 0.7 * rng.random(3)).round(3).tolist()}


def _ground_height(spec: dict):
    """The ground's height at (x, z) for a description: the terrain's, else 0."""
    terrain = next((s["terrain"] for s in spec["shapes"] if s["type"] == "terrain"), None)
    if terrain is None:
        return lambda x, z: 0.0
    return lambda x, z: float(terrain_height(terrain, x, z))


def _clutter_region(spec: dict) -> tuple[np.ndarray, float]:
    """(centre (x, z), radius) of the ground where clutter goes: the turntable, the room's
    floor, or ahead of the walkthrough outdoors."""
    cams = np.asarray(spec["cameras"]["c2w"])
    if spec["kind"] == "object":
        return np.zeros(2), 0.9
    if spec["kind"] == "indoor":
        floor = np.asarray(next(s for s in spec["shapes"] if s["name"] == "floor")["to_world"])
        half = min(np.linalg.norm(floor[:3, 0]), np.linalg.norm(floor[:3, 1]))
        return floor[[0, 2], 3], 0.9 * half
    ahead = cams[:, :3, 2].mean(0)
    centre = cams[:, :3, 3].mean(0) + 6.0 * ahead / max(np.linalg.norm(ahead[[0, 2]]), 1e-6)
    return centre[[0, 2]], 6.0


def clutter(spec: dict, rng: np.random.Generator) -> list[dict]:
    """Many small photo-textured objects (rocks, boxes, sticks) on the ground of ``spec``,
    off the camera path (``CLUTTER``)."""
    (lo, hi), (s_lo, s_hi), clearance = CLUTTER[spec["kind"]]
    centre, radius = _clutter_region(spec)
    path = np.asarray(spec["cameras"]["c2w"])[:, :3, 3][:, [0, 2]]
    ground = _ground_height(spec)
    out = []
    for _ in range(int(rng.integers(lo, hi)) * 4):
        if len(out) == hi:
            break
        r, a = radius * math.sqrt(rng.random()), rng.uniform(0, 2 * math.pi)
        xz = centre + r * np.array([math.cos(a), math.sin(a)])
        if clearance and (np.linalg.norm(path - xz, axis=1) < clearance).any():
            continue
        size, g = float(rng.uniform(s_lo, s_hi)), ground(*xz)
        material = _photo_material(rng, {"type": "plain", "rgb": [0.5, 0.5, 0.5]})
        name, shape = f"clutter{len(out)}", int(rng.integers(3))
        if shape == 0:  # a rock: a sphere, partly sunk (Mitsuba's sphere scales uniformly)
            out.append(_sphere(name, [xz[0], g + 0.3 * size, xz[1]], 0.6 * size, material))
        elif shape == 1:
            half = size * rng.uniform([0.4, 0.3, 0.4], [1.0, 1.0, 1.0])
            out.append(_box(name, [xz[0], g + half[1], xz[1]], half, material,
                            yaw=rng.uniform(0, 90)))
        else:  # a stick lying on the ground
            m = (translate([xz[0], g + 0.1 * size, xz[1]])
                 @ rotate([0, 1, 0], rng.uniform(0, 360))  # the cylinder's axis (z) is level
                 @ scale([0.1 * size, 0.1 * size, 2 * size]))
            out.append(_shape(name, "cylinder", m, material))
    return out


def hand_held(c2w: list, rng: np.random.Generator, rotation_deg: float, translation: float
              ) -> list:
    """Each camera turned by a small random rotation (``rotation_deg`` standard deviation
    about a random axis) and moved by ``translation`` (standard deviation per axis)."""
    out = []
    for c in c2w:
        c = np.asarray(c, dtype=np.float64)
        turn = rotate(rng.normal(size=3), rng.normal(0.0, rotation_deg))[:3, :3]
        m = c.copy()
        m[:3, :3] = c[:3, :3] @ turn
        m[:3, 3] = c[:3, 3] + rng.normal(0.0, translation, 3)
        out.append(np.round(m, 7).tolist())
    return out


def camera_effects_spec(rng: np.random.Generator) -> dict:
    """A scene's camera effects (``render.camera_effects``): blur sizes are fractions of the
    image width, so a set renders alike at any resolution."""
    return {"seed": int(rng.integers(2**31)), "key": PHOTO_KEY,
            # mostly sharp (a photo downsampled to 64-128 pixels is), now and then soft
            "defocus": round(float(rng.uniform(0.0, 0.006) * (rng.random() < 0.5)), 5),
            "motion": round(float(rng.uniform(0.0, 0.008) * (rng.random() < 0.5)), 5),
            "vignetting": round(float(rng.uniform(0.0, 0.45)), 3),
            "exposure_sd_ev": 0.15, "white_balance_sd": 0.04,
            "noise": round(float(rng.uniform(0.003, 0.02)), 4),
            "jpeg_quality": int(rng.integers(70, 96))}


def photographic(spec: dict, rng: np.random.Generator) -> dict:
    """The photographic appearance of a description (module docstring): its shapes
    re-dressed, clutter added, lights, integrator and cameras made photographic."""
    shapes = [{**s, "material": _photo_material(rng, s["material"])} for s in spec["shapes"]]
    shapes += clutter(spec, rng)
    lights = []
    for light in spec["lights"]:
        if light["type"] == "constant":
            lights.append(environment_spec(rng, 1.3 * float(np.mean(light["radiance"]))))
        elif light["type"] == "area":  # larger lamps, the same power: soft shadows
            to_world = np.asarray(light["to_world"]) @ scale([LAMP_SCALE, LAMP_SCALE, 1.0])
            lights.append({**light, "to_world": np.round(to_world, 6).tolist(),
                           "radiance": round(light["radiance"] / LAMP_SCALE**2, 3)})
        else:
            lights.append(light)
    focal = math.exp(rng.uniform(*np.log(PHOTO_FOCAL_MM)))
    cams = np.asarray(spec["cameras"]["c2w"])
    extent = float(np.linalg.norm(cams[:, :3, 3] - cams[:, :3, 3].mean(0), axis=1).max())
    c2w = hand_held(spec["cameras"]["c2w"], rng, rng.uniform(0.3, 1.5),
                    0.02 * max(extent, 0.1))
    return {**spec, "version": PHOTO_VERSION, "shapes": shapes, "lights": lights,
            "appearance": "photographic",
            "integrator": {"type": "path", "max_depth": PHOTO_MAX_DEPTH},
            "cameras": {"c2w": c2w, "fov_x_deg": round(math.degrees(2 * math.atan(18 / focal)),
                                                      4)},
            "camera_effects": camera_effects_spec(rng),
            "tags": [*spec["tags"], "photographic"]}


def make_spec(kind: str, seed: int, frames: int, appearance: str = "diffuse") -> dict:
    """The description of one procedural scene (deterministic for ``(kind, seed, frames,
    appearance)``; both appearances of a seed share shapes and cameras).

    Examples:
        >>> spec = make_spec("indoor", 0, 4)
        >>> spec["kind"], len(spec["cameras"]["c2w"]), spec == make_spec("indoor", 0, 4)
        ('indoor', 4, True)
        >>> shiny = make_spec("indoor", 0, 4, "view-dependent")
        >>> shiny["cameras"] == spec["cameras"], shiny["integrator"]["type"]
        (True, 'path')
    """
    if kind not in BUILDERS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    if appearance not in APPEARANCES:
        raise ValueError(f"appearance must be one of {APPEARANCES}, got {appearance!r}")
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    rng = np.random.default_rng([seed, KINDS.index(kind)])
    s = BUILDERS[kind](rng, frames)
    spec = {"version": SPEC_VERSION, "kind": kind, "seed": seed, "shapes": s["shapes"],
            "lights": s["lights"],
            "cameras": {"c2w": [np.round(c, 7).tolist() for c in s["cameras"]],
                        "fov_x_deg": round(s["fov_x_deg"], 4)},
            "near_far": s["near_far"], "tags": s["tags"]}
    if appearance == "photographic":  # its own stream too (the geometry's is untouched)
        return photographic(spec, np.random.default_rng([seed, KINDS.index(kind), 2]))
    if appearance != "diffuse":  # its own random stream: the geometry stays the same (and
        # both shiny appearances make the same surfaces shiny, under the same sky)
        spec = view_dependent(spec, np.random.default_rng([seed, KINDS.index(kind), 1]),
                              appearance)
    return spec
