"""The Mitsuba plugins (``usplat_dr.plugins``): the sensor mapping against Mitsuba's own rays,
``usplat_splat`` renders and gradients through ``mi.render`` against the torch API fed from
independent float64 constructions (look-at camera, covariance from scale and quaternion)."""

import math

import drjit as dr  # (conftest imported usplat_dr first: libLLVM chosen)
import numpy as np
import pytest
import torch

from usplat_dr.render import RasterSettings, rasterize

mi = pytest.importorskip("mitsuba")  # Mitsuba's plugins; a GPU image without it skips them

from usplat_dr import plugins  # noqa: E402 (after the skip: it imports Mitsuba)


@pytest.fixture(autouse=True)
def _variant():
    mi.set_variant("llvm_ad_rgb")


def look_at_c2w(origin, target, up) -> np.ndarray:
    """OpenCV camera-to-world (x right, y down, z forward), float64, from its definition."""
    o, t, u = (np.asarray(v, dtype=np.float64) for v in (origin, target, up))
    z = (t - o) / np.linalg.norm(t - o)
    x = np.cross(z, u)
    x /= np.linalg.norm(x)  # right: forward x up
    y = np.cross(z, x)  # down
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, o
    return m


def quat_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def gaussians(n=300, degree=2, seed=0):
    rng = np.random.default_rng(seed)
    return {"means": rng.normal(size=(n, 3)) * [0.8, 0.8, 0.5],
            "scales": np.exp(rng.normal(size=(n, 3)) * 0.3 - 2.5),
            "quats": rng.normal(size=(n, 4)),
            "opacities": rng.uniform(0.2, 0.95, n),
            "sh": rng.normal(size=(n, 3, (degree + 1) ** 2)) * 0.3}


SENSOR = dict(origin=[0.3, -0.4, 4.0], target=[0.0, 0.1, 0.0], up=[0.0, 1.0, 0.0])


def scene_dict(g, integrator=None, width=48, height=40, fov=45.0, **sensor_extra):
    to_world = mi.ScalarTransform4f().look_at(**SENSOR)
    return {"type": "scene",
            "integrator": {"type": "usplat_splat", "srgb_primitives": False,
                           **(integrator or {})},
            "sensor": {"type": "perspective", "fov": fov, "to_world": to_world,
                       "near_clip": 0.5, "far_clip": 50.0,
                       "film": {"type": "hdrfilm", "width": width, "height": height,
                                "pixel_format": "rgb", "rfilter": {"type": "box"}},
                       **sensor_extra},
            "gaussians": plugins.gaussians_to_ellipsoids(
                g["means"], g["scales"], g["quats"], g["opacities"], g["sh"], sh_basis="3dgs")}


def torch_inputs(g, width=48, height=40, fov=45.0, requires_grad=False):
    """The same scene for ``rasterize``, built independently in float64."""
    c2w = look_at_c2w(**SENSOR)
    f = 0.5 / math.tan(math.radians(fov) / 2)  # fov along x (Mitsuba's default fov_axis)
    k = np.array([[f, 0, 0.5], [0, f * width / height, 0.5], [0, 0, 1]])
    r = quat_xyzw_to_matrix(g["quats"])
    t = {k_: torch.tensor(v, dtype=torch.float32) for k_, v in g.items()}
    if requires_grad:
        for v in t.values():
            v.requires_grad_(True)
    q = t["quats"] / t["quats"].norm(dim=-1, keepdim=True)
    x, y, z, w = q.unbind(-1)
    rot = torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)],
        1)
    assert np.allclose(rot.detach().numpy(), r, atol=1e-6)  # the two formulas agree
    cov = rot @ torch.diag_embed(t["scales"] ** 2) @ rot.transpose(-1, -2)
    args = (torch.tensor(c2w, dtype=torch.float32)[None],
            torch.tensor(k, dtype=torch.float32)[None],
            torch.tensor([0.5]), torch.tensor([50.0]), (height, width), torch.zeros(1, 3),
            t["means"][None], cov[None], t["sh"][None], t["opacities"][None])
    return args, t


def test_sensor_mapping_matches_mitsubas_rays():
    """Pixels of a cropped, off-centre, fov_axis=y sensor: Mitsuba's ray through a pixel
    centre lands on that pixel under our camera."""
    sensor = mi.load_dict({
        "type": "perspective", "fov": 50, "fov_axis": "y", "principal_point_offset_x": 0.07,
        "principal_point_offset_y": -0.05, "near_clip": 0.3,
        "to_world": mi.ScalarTransform4f().look_at(**SENSOR),
        "film": {"type": "hdrfilm", "width": 64, "height": 48, "crop_offset_x": 8,
                 "crop_offset_y": 4, "crop_width": 40, "crop_height": 30}})
    cam = plugins.sensor_camera(sensor)
    h, w = cam["image_shape"]
    assert (h, w) == (30, 40)
    rng = np.random.default_rng(1)
    uv = rng.uniform(0.05, 0.95, size=(20, 2))
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(uv[:, 0], uv[:, 1]), mi.Point2f(0.5))
    p = np.stack([np.array(ray.o[i]) + 3.0 * np.array(ray.d[i]) for i in range(3)], -1)
    w2c = np.linalg.inv(cam["extrinsics"])
    pc = p @ w2c[:3, :3].T + w2c[:3, 3]
    k = cam["intrinsics"]
    u = k[0, 0] * pc[:, 0] / pc[:, 2] + k[0, 2]
    v = k[1, 1] * pc[:, 1] / pc[:, 2] + k[1, 2]
    # float32 rays: 1e-5 of the image
    assert np.allclose(u, uv[:, 0], atol=1e-5) and np.allclose(v, uv[:, 1], atol=1e-5)
    assert cam["near"] == pytest.approx(0.3)


def test_plugin_render_equals_the_torch_api():
    g = gaussians()
    scene = mi.load_dict(scene_dict(g))
    ours = np.array(mi.render(scene))
    args, _ = torch_inputs(g)
    ref = rasterize(*args).color[0].permute(1, 2, 0).numpy()
    assert ours.shape == (40, 48, 3)
    assert ref.std() > 0.05  # the Gaussians fill the view
    # same rasteriser, float32 camera built two ways (look-at vs float64): 1e-4
    assert np.abs(ours - ref).max() < 1e-4
    # sRGB primitives (the default) are converted to linear for the film; alpha with rgba
    d = scene_dict(g, {"srgb_primitives": True, "background": [0.2, 0.3, 0.4]})
    d["sensor"]["film"]["pixel_format"] = "rgba"
    rgba = np.array(mi.render(mi.load_dict(d)))
    args = (*args[:5], torch.tensor([[0.2, 0.3, 0.4]]), *args[6:])
    out = rasterize(*args)
    c = out.color[0].permute(1, 2, 0).numpy().astype(np.float64)
    linear = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    assert np.abs(rgba[..., :3] - linear).max() < 1e-4
    assert np.abs(rgba[..., 3] - out.alpha[0].numpy()).max() < 1e-4


def test_gradients_through_mi_render_match_the_torch_api():
    g = gaussians(n=120, degree=1, seed=2)
    scene = mi.load_dict(scene_dict(g))
    params = mi.traverse(scene)
    keys = ["gaussians.data", "gaussians.opacities", "gaussians.sh_coeffs"]
    for k in keys:
        dr.enable_grad(params[k])
    params.update()
    image = mi.render(scene, params)
    weights = np.random.default_rng(3).normal(size=(40, 48, 3))
    dr.backward(dr.sum(image * mi.TensorXf(weights.astype(np.float32)), axis=None))
    grads = {k: np.array(dr.grad(params[k])) for k in keys}

    args, t = torch_inputs(g, requires_grad=True)
    color = rasterize(*args).color[0].permute(1, 2, 0)
    (color * torch.tensor(weights, dtype=torch.float32)).sum().backward()
    n = 120
    data = grads["gaussians.data"].reshape(n, 10)
    expect = {"centres": (data[:, :3], t["means"].grad), "scales": (data[:, 3:6], t["scales"].grad),
              "quaternions": (data[:, 6:], t["quats"].grad),
              "opacities": (grads["gaussians.opacities"], t["opacities"].grad),
              "sh": (grads["gaussians.sh_coeffs"].reshape(n, 4, 3),
                     t["sh"].grad.transpose(1, 2))}
    for name, (ours, ref) in expect.items():
        ref = ref.numpy().reshape(ours.shape)
        scale = np.abs(ref).max()
        assert scale > 0, name
        # float32 gradients of the same computation reached two ways: 1e-3 of the largest
        assert np.abs(ours - ref).max() < 1e-3 * scale, name


def test_model_gaussians_round_trip_through_mitsuba():
    """A model's Gaussians (MVSplat SH basis, covariance matrices) as an ellipsoids shape and
    back: covariances and renders preserved."""
    from usplat_dr.model.types import Gaussians

    gen = torch.Generator().manual_seed(4)
    n = 200
    means = torch.randn(1, n, 3, generator=gen) * 0.5
    a = torch.randn(1, n, 3, 3, generator=gen) * 0.05
    cov = a @ a.transpose(-1, -2) + 1e-4 * torch.eye(3)
    sh = torch.randn(1, n, 3, 9, generator=gen) * 0.3
    op = torch.rand(1, n, generator=gen)
    model_g = Gaussians(means=means, covariances=cov, harmonics=sh, opacities=op,
                        scales=torch.ones(1, n, 3), rotations=torch.zeros(1, n, 4))
    shape = mi.load_dict(plugins.model_gaussians_to_ellipsoids(model_g))
    back = plugins.ellipsoids_to_gaussians(shape)
    # float32 eigen-decomposition and quaternion: 1e-6 absolute on entries of ~1e-2
    assert torch.allclose(back["covariances"], cov[0], atol=1e-6)
    assert torch.equal(back["means"], means[0]) and torch.equal(back["opacities"], op[0])
    c2w = torch.tensor(look_at_c2w(**SENSOR), dtype=torch.float32)[None]
    k = torch.tensor([[[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1]]])
    cam = (c2w, k, torch.tensor([0.5]), torch.tensor([50.0]), (32, 32), torch.zeros(1, 3))
    model_render = rasterize(*cam, means, cov, sh, op, RasterSettings(sh_basis="mvsplat"))
    plugin_side = rasterize(*cam, back["means"][None], back["covariances"][None],
                            back["harmonics"][None], back["opacities"][None])
    # SH basis change is exact up to float32 (<1e-5); covariances differ by 1e-6
    assert (model_render.color - plugin_side.color).abs().max() < 1e-4


def test_plugin_conventions_and_errors():
    integrator = mi.load_dict({"type": "usplat_splat", "tile_size": 8})
    assert "tile_size = 8" in integrator.to_string()
    assert "background" in mi.traverse(integrator)
    assert "pluginparameters" in plugins.integrator_class().__doc__
    with pytest.raises(Exception, match="tile_size"):
        mi.load_dict({"type": "usplat_splat", "tile_size": 5})
    with pytest.raises(Exception, match="sh_basis"):
        mi.load_dict({"type": "usplat_splat", "sh_basis": "e3nn"})
    g = gaussians(n=5)
    d = scene_dict(g)
    del d["gaussians"]["opacities"]
    scene = mi.load_dict(d)
    # (mi.render wraps errors of the integrator in dr.custom's RuntimeError)
    with pytest.raises(ValueError, match="opacities"):
        scene.integrator().render(scene, scene.sensors()[0])
    d = scene_dict(g)
    d["sensor"]["type"] = "orthographic"
    del d["sensor"]["fov"]
    scene = mi.load_dict(d)
    with pytest.raises(ValueError, match="perspective"):
        scene.integrator().render(scene, scene.sensors()[0])


def test_inverse_rendering_example_raises_held_out_psnr(tmp_path):
    """train/examples/mitsuba_inverse.py (Mitsuba's loop through usplat_splat), a short run."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).parents[2] / "train" / "examples" / "mitsuba_inverse.py"
    spec = importlib.util.spec_from_file_location("mitsuba_inverse", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    result = module.run(iterations=40, out=tmp_path, progress=False)
    # measured: 10.4 -> 26.0 dB after 60 steps (grey, inflated initial Gaussians); 40 steps
    # and an 8 dB margin leave room for platform differences
    assert result["psnr_after"] > result["psnr_before"] + 8
    assert Path(result["renders"]).is_file()


def test_docs_rasteriser_snippets_run(tmp_path, monkeypatch):
    """docs/rasteriser.md's snippets (from Dr.Jit, from Mitsuba) run as written, each block on
    its own (the README's torch snippet runs in tests/test_readme.py)."""
    import re
    from pathlib import Path

    text = (Path(__file__).parents[2] / "docs" / "rasteriser.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.DOTALL)
    assert len(blocks) == 2 and "mi.render" in blocks[1]
    monkeypatch.chdir(tmp_path)
    for code in blocks:
        # mi.util.write_bitmap resolves a relative name through Mitsuba's file resolver, whose
        # base is not always the current folder (a stray gaussians.png in the repository):
        # the same call with the name made absolute
        code = code.replace('"gaussians.png"', repr(str(tmp_path / "gaussians.png")))
        exec(compile(code, "rasteriser.md", "exec"), {})  # noqa: S102 (the docs' own code)
    # written synchronously (write_async=False): Mitsuba's default asynchronous write once
    # missed a 60 s wait on a loaded machine in CI
    assert (tmp_path / "gaussians.png").is_file()
