"""Camera conventions pinned against Mitsuba: one OpenCV <-> Mitsuba conversion, sphere
centres at the predicted pixel, analytic plane depths, and our rasteriser's tiny Gaussians
on Mitsuba surfaces at the right pixels."""

import math

import numpy as np
import pytest
import torch

from usplat_dr.data.synth.render import intrinsics_for, render_spec, set_variant, trace_depth
from usplat_dr.data.synth.scenes import look_at_np, make_spec, rotate, scale, translate
from usplat_dr.geometry.cameras import mitsuba_to_opencv_c2w, opencv_c2w_to_mitsuba

pytest.importorskip("mitsuba")  # these tests are Mitsuba's; a GPU image without it skips them
mi = set_variant("llvm")


def project_ref(c2w: np.ndarray, k: np.ndarray, p: np.ndarray, hw) -> np.ndarray:
    """Pixel coordinates of world points with the OpenCV pinhole, in float64 from the
    equations (x right, y down, pixel (i, j) centred at (j + 0.5, i + 0.5))."""
    q = (np.linalg.inv(c2w) @ np.c_[p, np.ones(len(p))].T).T
    return np.stack([(k[0, 0] * q[:, 0] / q[:, 2] + k[0, 2]) * hw[1],
                     (k[1, 1] * q[:, 1] / q[:, 2] + k[1, 2]) * hw[0]], -1)


def mitsuba_uv(sensor, points: np.ndarray) -> np.ndarray:
    """Mitsuba's own projection of world points (``Sensor.sample_direction``), in pixels."""
    it = mi.Interaction3f()
    it.p = mi.Point3f(*[mi.Float(points[:, i].astype(np.float32)) for i in range(3)])
    ds, _ = sensor.sample_direction(it, mi.Point2f(0.5, 0.5))
    return np.array(ds.uv, dtype=np.float64).T  # Dr.Jit arrays convert as [2, N]


def sensor_dict(c2w, fov_x, hw, spp=16):
    return {"type": "perspective", "fov": fov_x, "fov_axis": "x",
            "to_world": mi.ScalarTransform4f(opencv_c2w_to_mitsuba(c2w).tolist()),
            "film": {"type": "hdrfilm", "width": hw[1], "height": hw[0],
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": spp}}


def random_camera(rng) -> np.ndarray:
    eye = rng.uniform(-1, 1, 3) + [0, 0, -3]
    return look_at_np(eye, rng.uniform(-0.3, 0.3, 3), up=rng.uniform(-0.2, 0.2, 3) + [0, 1, 0])


def test_conversion_is_an_involution_and_matches_mitsuba_projection():
    set_variant("llvm")
    rng = np.random.default_rng(0)
    hw = (48, 64)  # not square: fov_axis x and the aspect must agree too
    for _ in range(3):
        c2w = random_camera(rng)
        np.testing.assert_array_equal(mitsuba_to_opencv_c2w(opencv_c2w_to_mitsuba(c2w)), c2w)
        sensor = mi.load_dict(sensor_dict(c2w, 55.0, hw))
        pts = rng.uniform(-0.8, 0.8, (20, 3))
        ours = project_ref(c2w, intrinsics_for(55.0, hw), pts, hw)
        # float32 inside Mitsuba: ~1e-5 relative of ~100 px coordinates.
        np.testing.assert_allclose(mitsuba_uv(sensor, pts), ours, atol=2e-3)


def test_sphere_centre_lands_at_the_projected_pixel():
    """An emissive sphere rendered by Mitsuba: its intensity centroid is within half a pixel
    of the centre's projection by our pinhole model."""
    set_variant("llvm")
    rng = np.random.default_rng(1)
    hw = (96, 128)
    for _ in range(3):
        c2w = random_camera(rng)
        centre = rng.uniform(-0.5, 0.5, 3)
        scene = mi.load_dict({
            "type": "scene", "integrator": {"type": "direct"},
            "sensor": sensor_dict(c2w, 50.0, hw, spp=64),
            "ball": {"type": "sphere", "center": centre.tolist(), "radius": 0.12,
                     "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}})
        img = np.array(mi.render(scene))[..., 0].astype(np.float64)
        ys, xs = np.mgrid[0:hw[0], 0:hw[1]] + 0.5
        centroid = np.array([(img * xs).sum(), (img * ys).sum()]) / img.sum()
        pred = project_ref(c2w, intrinsics_for(50.0, hw), centre[None], hw)[0]
        # Perspective shifts a sphere's silhouette centre off the projected centre by
        # ~f (r/d)^2 tan(theta) < 0.1 px here; anti-aliasing noise is far smaller.
        assert np.abs(centroid - pred).max() < 0.5, (centroid, pred)


@pytest.mark.parametrize("tilt", [0.0, 35.0])
def test_plane_depth_is_analytic(tilt):
    """trace_depth on a plane: camera-space z equals the analytic ray-plane intersection."""
    set_variant("llvm")
    hw = (40, 56)
    c2w = look_at_np([0.2, 0.1, -0.5], [0.2, 0.1, 2.0], up=[0, 1, 0])  # looking along +Z
    d = 2.5
    # A large rectangle at z = d (world), rotated by ``tilt`` about the world Y axis.
    to_world = translate([0.2, 0.1, d]) @ rotate([0, 1, 0], tilt) @ scale(20.0)
    scene = mi.load_dict({"type": "scene", "plane": {"type": "rectangle",
                                                     "to_world": mi.ScalarTransform4f(
                                                         to_world.tolist())}})
    k = intrinsics_for(70.0, hw)
    depth, _ = trace_depth(mi, scene, c2w, k, hw)
    # Analytic: in camera coordinates the plane passes through (0, 0, d + 0.5) with normal
    # n = R^T (sin(tilt), 0, cos(tilt)); the ray through pixel (x, y) has direction
    # (x', y', 1), so z = (n . p0) / (n . (x', y', 1)).
    t = math.radians(tilt)
    n = np.linalg.inv(c2w[:3, :3]) @ np.array([math.sin(t), 0, math.cos(t)])
    p0 = np.array([0.0, 0.0, d + 0.5])
    jj, ii = np.meshgrid(np.arange(hw[1]) + 0.5, np.arange(hw[0]) + 0.5)
    dirs = np.stack([(jj / hw[1] - 0.5) / k[0, 0], (ii / hw[0] - 0.5) / k[1, 1],
                     np.ones_like(jj)], -1)
    z_ref = (n @ p0) / (dirs @ n)
    np.testing.assert_allclose(depth, z_ref, rtol=2e-5)  # float32 ray tracing


def test_depth_is_infinite_where_nothing_is_hit():
    set_variant("llvm")
    scene = mi.load_dict({"type": "scene", "ball": {"type": "sphere", "center": [0, 0, 3],
                                                    "radius": 0.5}})
    depth, _ = trace_depth(mi, scene, np.eye(4), intrinsics_for(60.0, (16, 16)), (16, 16))
    assert np.isinf(depth[0, 0]) and np.isfinite(depth[8, 8])
    assert depth[8, 8] == pytest.approx(3 - math.sqrt(0.25 - 0.0), rel=2e-2)  # off-centre ray


def test_tiny_gaussians_on_mitsuba_surfaces_render_at_the_right_pixels():
    """Points on the surfaces of a synthetic room (from Mitsuba's depth in view 0), rendered
    by our rasteriser in another view as tiny opaque Gaussians, appear where Mitsuba's sensor
    projects them, at the depth Mitsuba sees there."""
    from usplat_dr.render import rasterize

    set_variant("llvm")
    hw = (64, 64)
    spec = make_spec("indoor", 3, 6)
    _, depths, _, k = render_spec(spec, hw, spp=1)
    c2w = np.asarray(spec["cameras"]["c2w"])
    rng = np.random.default_rng(0)
    ii, jj = rng.integers(8, 56, 24), rng.integers(8, 56, 24)
    z = depths[0][ii, jj].astype(np.float64)
    cam = np.stack([((jj + 0.5) / hw[1] - k[0, 2]) / k[0, 0] * z,
                    ((ii + 0.5) / hw[0] - k[1, 2]) / k[1, 1] * z, z, np.ones_like(z)], -1)
    world = (cam @ c2w[0].T)[:, :3]

    view = 2
    scene = mi.load_dict({"type": "scene", "sensor": sensor_dict(c2w[view], spec["cameras"][
        "fov_x_deg"], hw)})
    uv_mi = mitsuba_uv(scene.sensors()[0], world)

    n = len(world)
    f_px = k[0, 0] * hw[1]
    z_view = (np.c_[world, np.ones(n)] @ np.linalg.inv(c2w[view]).T)[:, 2]
    sigma = 0.2 * z_view / f_px  # 0.2 px footprint: the 0.3 px^2 dilation dominates
    cov = torch.tensor(sigma[:, None, None] ** 2 * np.eye(3), dtype=torch.float32)[:, None]
    out = rasterize(torch.tensor(c2w[view], dtype=torch.float32).expand(n, 4, 4),
                    torch.tensor(k, dtype=torch.float32).expand(n, 3, 3),
                    torch.full((n,), 0.1), torch.full((n,), 100.0), hw, torch.zeros(n, 3),
                    torch.tensor(world, dtype=torch.float32)[:, None], cov,
                    torch.ones(n, 1, 3, 1), torch.full((n, 1), 0.99))
    alpha = out.alpha.numpy().astype(np.float64)
    ys, xs = np.mgrid[0:hw[0], 0:hw[1]] + 0.5
    checked = 0
    for g in range(n):
        if not ((uv_mi[g] >= 3) & (uv_mi[g] <= np.array(hw[::-1]) - 3)).all():
            assert alpha[g, 3:-3, 3:-3].max() < 0.5  # nothing rendered well inside either
            continue
        centroid = np.array([(alpha[g] * xs).sum(), (alpha[g] * ys).sum()]) / alpha[g].sum()
        # Within half a pixel of Mitsuba's projection (the alpha footprint is symmetric; the
        # 1/255 cut and the image border clip it by < 0.1 px for points >= 3 px inside).
        assert np.abs(centroid - uv_mi[g]).max() < 0.5, (g, centroid, uv_mi[g])
        px = np.floor(uv_mi[g]).astype(int)
        if depths[view][px[1], px[0]] < z_view[g] * 0.97:
            continue  # hidden behind nearer geometry in this view: nothing to compare
        rendered_z = out.depth[g, px[1], px[0]].item() / out.alpha[g, px[1], px[0]].item()
        assert rendered_z == pytest.approx(z_view[g], rel=1e-4)
        # The Mitsuba surface at that pixel is the point's surface: within the depth change
        # across one pixel of a grazing surface (5%).
        assert depths[view][px[1], px[0]] == pytest.approx(z_view[g], rel=0.05)
        checked += 1
    assert checked >= 8  # most of the 24 points are visible in a nearby frame
