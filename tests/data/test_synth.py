"""``usplat synth``: determinism, the chunk format, splits, re-rendering, loading."""

import hashlib
import json

import numpy as np
import pytest
import torch

from usplat_dr.cli import main
from usplat_dr.data import ChunkDataset, ViewSamplerEvaluationCfg, dataset_cfg, read_chunk
from usplat_dr.data.chunks import decode_image
from usplat_dr.data.synth import SPLITS, render_spec, synthesize
from usplat_dr.data.synth.render import MISS
from usplat_dr.data.synth.splits import disoccluded_fraction

ARGS = dict(scenes=3, frames=8, resolution=(16, 20), seed=7, spp=4, progress=False)


@pytest.fixture(scope="module")
def synth_set(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth")
    synthesize(out, **ARGS)
    return out


def _digest(root) -> dict:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_seed_same_bytes(synth_set, tmp_path):
    # Byte equality, not a tolerance: scene loading, emitter order and sampling are fixed by
    # the seed (area lamps are disks because Mitsuba reorders meshes between runs, which
    # once made this fail in CI), and two worker processes must not change a byte either.
    synthesize(tmp_path, **ARGS, jobs=2)
    assert _digest(tmp_path) == _digest(synth_set)
    other = tmp_path / "other"
    synthesize(other, **{**ARGS, "seed": 8})
    assert _digest(other)["test/000000.torch"] != _digest(synth_set)["test/000000.torch"]


def test_records_have_the_documented_structure(synth_set):
    (chunk,) = sorted((synth_set / "test").glob("*.torch"))
    scenes = read_chunk(chunk)
    index = json.loads((synth_set / "test" / "index.json").read_text())
    keys = ["indoor_7_00000", "object_7_00002", "outdoor_7_00001"]  # kinds round-robin
    assert sorted(s["key"] for s in scenes) == sorted(index) == keys
    for s in scenes:
        assert s["cameras"].shape == (8, 18) and str(s["cameras"].dtype) == "torch.float32"
        assert s["timestamps"].tolist() == list(range(8))
        assert len(s["images"]) == 8 and decode_image(s["images"][0]).shape == (3, 16, 20)
        assert s["depths"].shape == (8, 16, 20) and str(s["depths"].dtype) == "torch.float16"
        assert s["materials"].shape == (8, 16, 20)
        # Misses are exactly where the depth is infinite.
        assert np.array_equal(np.isinf(s["depths"].float().numpy()),
                              s["materials"].numpy() == MISS)
        assert s["mitsuba"]["kind"] in s["tags"]


def test_stored_description_re_renders(synth_set):
    scene = read_chunk(synth_set / "test" / "000000.torch")[1]
    images, depths, _, _ = render_spec(scene["mitsuba"], (16, 20), spp=4,
                                       seed=int(scene["mitsuba"]["seed"]))
    stored = np.stack([decode_image(im).permute(1, 2, 0).numpy() for im in scene["images"]])
    np.testing.assert_array_equal(images, stored)  # same description, seed, resolution
    np.testing.assert_array_equal(depths.astype(np.float16), scene["depths"].numpy())
    big, big_depths, _, _ = render_spec(scene["mitsuba"], (32, 40), spp=2, frames=[0])
    assert big.shape == (1, 32, 40, 3)
    # At twice the resolution, the 4 rays of a 2x2 block surround the small pixel's ray at
    # +-1/4 pixel: on smooth surfaces their mean depth equals it to second order. The median
    # over pixels (silhouette edges excluded) agrees to 1%.
    block = big_depths[0].reshape(16, 2, 20, 2).transpose(0, 2, 1, 3).reshape(16, 20, 4)
    both = np.isfinite(block).all(-1) & np.isfinite(depths[0])
    err = np.abs(block.mean(-1)[both] / depths[0][both] - 1)
    assert both.mean() > 0.3 and np.median(err) < 0.01


def test_splits_are_valid_index_files(synth_set):
    for split in SPLITS:
        index = json.loads((synth_set / f"evaluation_index_{split}.json").read_text())
        assert len(index) == 3
        for entry in index.values():
            if entry is None:
                continue
            frames = entry["context"] + entry["target"]
            assert all(0 <= f < 8 for f in frames) and len(entry["context"]) == 2
    wide = json.loads((synth_set / "evaluation_index_wide_baseline.json").read_text())
    std = json.loads((synth_set / "evaluation_index_standard.json").read_text())
    extra = json.loads((synth_set / "evaluation_index_extrapolation.json").read_text())
    for key in std:
        assert wide[key]["context"] == [0, 7]
        assert np.diff(wide[key]["context"]) > np.diff(std[key]["context"])
        lo, hi = extra[key]["context"]
        assert all(t < lo or t > hi for t in extra[key]["target"])  # outside the segment
        lo, hi = std[key]["context"]
        assert all(lo < t < hi for t in std[key]["target"])  # interpolation
    summary = json.loads((synth_set / "splits.json").read_text())
    assert summary["scenes_per_split"]["standard"] == 3
    assert (synth_set / "previews" / "indoor_7_00000.png").is_file()


def test_disocclusion_measure():
    """A fronto-parallel wall with a box in front: a camera sliding sideways sees wall pixels
    that the box hid from the first camera; the first camera sees everything of itself."""
    h, w = 20, 20
    k = np.array([[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1]])
    c2w = np.tile(np.eye(4), (2, 1, 1))
    c2w[1, 0, 3] = 1.0  # second camera 1 m to the right
    depth = np.full((2, h, w), 5.0)
    depth[0, 8:12, 8:12] = 2.0  # box in front of the wall, seen by camera 0
    depth[1, 8:12, 3:7] = 2.0  # a box seen by camera 1 only (not a consistent scene)
    assert disoccluded_fraction(0, [0], c2w, k, depth) == 0.0
    frac = disoccluded_fraction(1, [0], c2w, k, depth)
    # Wall pixels of camera 1 (depth 5, f = 20 px) land 4 px further right in camera 0: its
    # last 4 columns fall outside camera 0's frame (80 pixels), and the wall pixels of column
    # 7, rows 8-11, land on camera 0's box (4 pixels; columns 4-6 there are camera 1's own
    # box, which lands 10 px right, on wall camera 0 sees). 84 / 400 = 0.21 unseen.
    assert frac == pytest.approx(0.21)


def test_dataset_reads_a_synthetic_split(synth_set):
    cfg = dataset_cfg("synth", synth_set, image_shape=(16, 20), view_sampler=(
        ViewSamplerEvaluationCfg(str(synth_set / "evaluation_index_standard.json"))))
    examples = list(ChunkDataset(cfg, "test"))
    assert len(examples) == 3
    ex = examples[0]
    assert ex["target"]["depth"].shape == (len(ex["target"]["index"]), 16, 20)
    assert ex["context"]["near"][0].item() == pytest.approx(0.2)  # the indoor bounds
    assert ex["context"]["far"][0].item() == pytest.approx(20.0)


def test_cli_synth(tmp_path, capsys):
    assert main(["-q", "synth", "--out", str(tmp_path), "--scenes", "1", "--frames", "4",
                 "--image-shape", "8", "8", "--spp", "1", "--kind", "object"]) == 0
    assert "scenes per evaluation split" in capsys.readouterr().out
    assert (tmp_path / "test" / "index.json").is_file()
    for bad in (["--frames", "2"], ["--image-shape", "2", "8"], ["--kind", "space"]):
        with pytest.raises(SystemExit):
            main(["synth", "--out", str(tmp_path), *bad])


def test_cli_synth_chunk_scenes(tmp_path):
    assert main(["-q", "synth", "--out", str(tmp_path), "--scenes", "3", "--frames", "4",
                 "--image-shape", "8", "8", "--spp", "1", "--kind", "object", "--stage", "train",
                 "--chunk-scenes", "2", "--previews", "0"]) == 0
    chunks = sorted((tmp_path / "train").glob("*.torch"))
    assert [len(read_chunk(c)) for c in chunks] == [2, 1]
    index = json.loads((tmp_path / "train" / "index.json").read_text())
    assert sorted(index.values()) == ["000000.torch", "000000.torch", "000001.torch"]
    # the train stage's metadata is beside its chunks (the root's is the test stage's)
    assert json.loads((tmp_path / "train" / "synth.json").read_text())["chunk_scenes"] == 2
    with pytest.raises(SystemExit):
        main(["synth", "--out", str(tmp_path), "--chunk-scenes", "0"])
    with pytest.raises(ValueError, match="chunk_scenes"):
        synthesize(tmp_path, **{**ARGS, "chunk_scenes": 0})


@pytest.mark.parametrize("kind", ["indoor", "outdoor", "object"])
def test_view_dependent_appearance_keeps_geometry(kind):
    from usplat_dr.data.synth.scenes import GLOSSY_BASE, GROUND, SHINY_ROUGHNESS, make_spec

    plain, shiny = make_spec(kind, 11, 6), make_spec(kind, 11, 6, "view-dependent")
    assert shiny["cameras"] == plain["cameras"] and shiny["near_far"] == plain["near_far"]
    assert [(s["name"], s["to_world"]) for s in shiny["shapes"]] == [
        (s["name"], s["to_world"]) for s in plain["shapes"]]
    types = [s["material"]["type"] for s in shiny["shapes"]]
    assert sum(t in ("glossy", "conductor") for t in types) >= len(types) / 2
    for s in shiny["shapes"]:
        if s["name"] in GROUND:
            assert s["material"]["type"] == "glossy" and "texture" in s["material"]
    # camera, shiny surface, what it reflects, a light: the scene's reflections
    assert shiny["integrator"] == {"type": "path", "max_depth": 3}
    for s in shiny["shapes"]:  # near-mirror, and a clear coat's base darker than the diffuse
        m = s["material"]
        if m["type"] in ("glossy", "conductor"):
            assert SHINY_ROUGHNESS[0] <= m["roughness"] <= SHINY_ROUGHNESS[1] <= 0.05
        if m["type"] == "glossy" and "texture" in m:
            assert m["albedo"] == GLOSSY_BASE < 1
    light_types = [x["type"] for x in shiny["lights"]]
    assert "constant" not in light_types
    assert ("envmap" in light_types) == (kind != "indoor")  # a closed room sees no sky
    assert "view_dependent" in shiny["tags"] and "appearance" not in plain
    with pytest.raises(ValueError, match="appearance"):
        make_spec(kind, 11, 6, "shiny")


@pytest.mark.parametrize("kind", ["indoor", "outdoor", "object"])
def test_rough_glossy_is_the_view_dependent_appearance_with_rough_surfaces(kind):
    from usplat_dr.data.synth import scene_key
    from usplat_dr.data.synth.scenes import ROUGH_ROUGHNESS, make_spec

    mirror, rough = make_spec(kind, 11, 6, "view-dependent"), make_spec(kind, 11, 6,
                                                                         "rough-glossy")
    # the same geometry, cameras, lights and integrator; the same surfaces shiny and metal
    for key in ("cameras", "near_far", "lights", "integrator"):
        assert rough[key] == mirror[key], key
    assert [(s["name"], s["to_world"], s["material"]["type"]) for s in rough["shapes"]] == [
        (s["name"], s["to_world"], s["material"]["type"]) for s in mirror["shapes"]]
    shiny = [s["material"] for s in rough["shapes"]
             if s["material"]["type"] in ("glossy", "conductor")]
    assert shiny and all(ROUGH_ROUGHNESS[0] <= m["roughness"] <= ROUGH_ROUGHNESS[1]
                         for m in shiny)
    assert min(ROUGH_ROUGHNESS) >= 0.15 and max(ROUGH_ROUGHNESS) <= 0.4  # broad highlights
    assert rough["appearance"] == "rough-glossy"
    assert {"view_dependent", "rough"} <= set(rough["tags"]) and "rough" not in mirror["tags"]
    assert scene_key(kind, 11, 0, "rough-glossy").endswith("_rg")  # its own scenes


def test_view_dependent_set_is_deterministic_with_the_same_depths(synth_set, tmp_path):
    # As users run it: two `usplat synth` processes, one and two workers. Path tracing's
    # bytes depend on Dr.Jit's vector width (the portable pin, on in every `usplat` command,
    # fixes it; a process that rendered before pinning would differ), so fresh processes.
    import subprocess
    import sys

    from usplat_dr.data.synth.render import CONDUCTOR, GLOSSY

    def run(out, jobs):
        subprocess.run([sys.executable, "-m", "usplat_dr.cli", "-q", "synth", "--out", str(out),
                        "--scenes", "3", "--frames", "8", "--image-shape", "16", "20", "--seed",
                        "7", "--spp", "4", "--appearance", "view-dependent", "--jobs",
                        str(jobs)], check=True, capture_output=True)

    run(tmp_path / "a", 1)
    run(tmp_path / "b", 2)
    da, db = _digest(tmp_path / "a"), _digest(tmp_path / "b")
    assert da == db, [k for k in da if da[k] != db.get(k)]
    shiny = {s["key"]: s for s in read_chunk(tmp_path / "a" / "test" / "000000.torch")}
    plain = {s["key"]: s for s in read_chunk(synth_set / "test" / "000000.torch")}
    assert sorted(shiny) == sorted(k + "_vd" for k in plain)
    for key, s in plain.items():  # the same geometry: the same depth maps, bit for bit
        assert torch.equal(shiny[key + "_vd"]["depths"], s["depths"])
    codes = np.concatenate([s["materials"].numpy().ravel() for s in shiny.values()])
    assert np.isin(codes, [GLOSSY, CONDUCTOR]).mean() > 0.3
    assert json.loads((tmp_path / "a" / "synth.json").read_text())["appearance"] == (
        "view-dependent")
    with pytest.raises(ValueError, match="appearance"):
        synthesize(tmp_path / "c", **{**ARGS, "appearance": "shiny"})


def test_a_clear_coats_base_albedo_scales_the_texture_in_linear_rgb():
    # Mitsuba's own sRGB decoding of the 8-bit texture is the reference; 2e-7 is float32
    # rounding of values <= 1.
    from usplat_dr.data.synth.render import _texture, set_variant
    from usplat_dr.data.synth.textures import make_texture, random_texture_spec

    mi = set_variant("llvm")
    spec = random_texture_spec(np.random.default_rng(0), res=16)
    scaled = _texture(mi, {"texture": spec, "albedo": 0.5})["bitmap"]
    assert not scaled.srgb_gamma()  # linear values: Mitsuba must not decode them again
    linear = mi.Bitmap(make_texture(spec)).convert(mi.Bitmap.PixelFormat.RGB,
                                                   mi.Struct.Type.Float32, srgb_gamma=False)
    np.testing.assert_allclose(np.array(scaled), 0.5 * np.array(linear), atol=2e-7)
