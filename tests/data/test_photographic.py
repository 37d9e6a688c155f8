"""The photographic appearance (``usplat synth --appearance photographic``): the diffuse
scene's geometry kept and clutter added, photographic textures, hand-held cameras of 24-70 mm,
camera effects; deterministic per seed, its depth exact whatever the materials."""

import copy
import math

import numpy as np
import pytest

from usplat_dr.data.synth import render_spec, scene_key
from usplat_dr.data.synth.render import AUTO_EXPOSURE, camera_effects
from usplat_dr.data.synth.scenes import PHOTO_FOCAL_MM, PHOTO_KEY, make_spec
from usplat_dr.data.synth.textures import PHOTOS, make_texture, photo_texture_spec

#: Effects switched off: what ``camera_effects`` does then is auto exposure, sRGB and JPEG.
NO_EFFECTS = {"seed": 0, "key": PHOTO_KEY, "defocus": 0.0, "motion": 0.0, "vignetting": 0.0,
              "exposure_sd_ev": 0.0, "white_balance_sd": 0.0, "noise": 0.0,
              "jpeg_quality": 100}


@pytest.mark.parametrize("kind", ["indoor", "outdoor", "object"])
def test_the_diffuse_geometry_is_kept_and_clutter_added(kind):
    plain, photo = make_spec(kind, 5, 8), make_spec(kind, 5, 8, "photographic")
    assert photo == make_spec(kind, 5, 8, "photographic")  # deterministic per seed
    assert photo["near_far"] == plain["near_far"] and photo["appearance"] == "photographic"
    n = len(plain["shapes"])
    assert [(s["name"], s["to_world"]) for s in photo["shapes"][:n]] == [
        (s["name"], s["to_world"]) for s in plain["shapes"]]
    assert all(s["name"].startswith("clutter") for s in photo["shapes"][n:])
    assert len(photo["shapes"]) > n  # clutter
    textured = [s["material"] for s in photo["shapes"] if "texture" in s["material"]]
    assert sum(m["texture"]["pattern"] == "photo" for m in textured) >= len(photo["shapes"]) / 3
    # bump relief only on diffuse surfaces (a bumped rough plastic rendered NaN pixels)
    assert all(not s["material"].get("bump") or s["material"]["type"] == "textured"
               for s in photo["shapes"])
    # hand-held: every camera moved a little from the diffuse path, none far
    moved = np.linalg.norm(np.asarray(photo["cameras"]["c2w"])[:, :3, 3]
                           - np.asarray(plain["cameras"]["c2w"])[:, :3, 3], axis=1)
    assert (moved > 0).all() and moved.max() < 0.5
    # a focal length of 24-70 mm on 36 mm film: fov_x = 2 atan(18 / f)
    f = 18 / math.tan(math.radians(photo["cameras"]["fov_x_deg"]) / 2)
    assert PHOTO_FOCAL_MM[0] - 1e-3 <= f <= PHOTO_FOCAL_MM[1] + 1e-3
    assert photo["integrator"]["type"] == "path" and "camera_effects" in photo
    assert scene_key(kind, 5, 0, "photographic").endswith("_ph")


def test_photo_textures_are_deterministic_crops_of_shipped_photographs():
    rng = np.random.default_rng(0)
    specs = [photo_texture_spec(rng, res=32) for _ in range(20)]
    assert {s["image"] for s in specs} <= set(PHOTOS)
    assert "stereo_motorcycle" not in PHOTOS  # it scores the models' depth: never a texture
    for s in specs[:5]:
        a = make_texture(s)
        assert a.shape == (32, 32, 3) and a.dtype == np.uint8
        assert np.array_equal(a, make_texture(copy.deepcopy(s)))
        assert a.std() > 2  # a photograph's detail, not a flat colour
    with pytest.raises(ValueError, match="photo must be one of"):
        make_texture({**specs[0], "image": "retina"})


@pytest.mark.parametrize("level", [0.01, 0.05, 0.4])
def test_auto_exposure_brings_a_flat_grey_to_the_key(level):
    # a flat grey of any brightness becomes the key (0.18, middle grey) in linear light, so
    # sRGB(0.18) = 118/255 after the round trip: the gain key / level is inside AUTO_EXPOSURE
    # for these levels. JPEG at quality 100 of a flat image keeps the value exactly, and the
    # geometric mean's 1e-4 guard moves the key by 1e-4 / level <= 1%: within one level.
    assert AUTO_EXPOSURE[0] <= PHOTO_KEY / level <= AUTO_EXPOSURE[1]
    out = camera_effects(np.full((16, 24, 3), level), NO_EFFECTS, 0)
    want = (1.055 * PHOTO_KEY ** (1 / 2.4) - 0.055) * 255  # IEC 61966-2-1, from the equation
    assert np.abs(out.astype(float) - want).max() <= 1.0


def test_camera_effects_are_deterministic_per_frame_and_sanitise_nan():
    fx = {**NO_EFFECTS, "defocus": 0.02, "motion": 0.03, "vignetting": 0.4,
          "exposure_sd_ev": 0.2, "white_balance_sd": 0.05, "noise": 0.02, "jpeg_quality": 80}
    rng = np.random.default_rng(1)
    img = rng.random((32, 32, 3)) * 0.3
    img[3, 4] = np.nan  # a path tracer's rare NaN sample becomes black, not a broken cast
    a, b, c = (camera_effects(img, fx, f) for f in (2, 2, 3))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    # vignetting darkens the corners against the centre, on a flat image
    flat = camera_effects(np.full((32, 32, 3), 0.1), {**fx, "noise": 0.0, "motion": 0.0}, 0)
    assert flat[:4, :4].mean() < flat[14:18, 14:18].mean() - 5


def test_depth_is_the_geometrys_whatever_the_materials():
    # the photographic render's depth against the same description with every surface plain
    # grey, no bump, no effects, no clutter material: bump maps shade and blur blurs the image
    # only, so the depth maps are equal bit for bit
    spec = make_spec("indoor", 5, 4, "photographic")
    flat = copy.deepcopy(spec)
    flat.pop("camera_effects")
    for s in flat["shapes"]:
        s["material"] = {"type": "plain", "rgb": [0.5, 0.5, 0.5]}
    images, depths = render_spec(spec, (12, 16), spp=2, frames=[0, 3])[:2]
    flat_images, flat_depths = render_spec(flat, (12, 16), spp=2, frames=[0, 3])[:2]
    assert np.array_equal(depths, flat_depths) and np.isfinite(depths).all()  # a closed room
    assert images.dtype == np.uint8 and not np.array_equal(images, flat_images)
    again = render_spec(spec, (12, 16), spp=2, frames=[0, 3])[0]
    assert np.array_equal(images, again)  # deterministic per seed
