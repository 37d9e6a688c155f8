"""Parts of UniqueSplat's view-specific branch: the ResNet18
backbone E_H and Proj (epipolar sampling with cosine-correlation fusion)."""

import logging
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from usplat_dr.model.checkpoint import CheckpointMismatchError
from usplat_dr.model.hypernet.epipolar import EpipolarProjection, project, target_rays
from usplat_dr.model.hypernet.resnet import ResNet18


def test_resnet18_has_torchvisions_layout(tmp_path, caplog):
    net = ResNet18()
    # torchvision's resnet18: 11,689,512 parameters, 122 state-dict entries (BatchNorm
    # running statistics included), published numbers independent of this code.
    assert sum(p.numel() for p in net.parameters()) == 11_689_512
    assert len(net.state_dict()) == 122
    path = tmp_path / "resnet18.pth"
    torch.save(ResNet18().state_dict(), path)
    assert net.load_torchvision(path)
    bad = {k: v for k, v in net.state_dict().items() if k != "fc.bias"}
    torch.save(bad, path)
    with pytest.raises(CheckpointMismatchError, match="fc.bias"):
        ResNet18().load_torchvision(path)
    with caplog.at_level(logging.WARNING):
        assert not ResNet18().load_torchvision(tmp_path / "missing.pth")
    assert "random initialisation" in caplog.text
    # A truncated feature extractor takes its part of a full file and ignores the rest.
    torch.save(net.state_dict(), path)
    part = ResNet18(num_classes=None, stages=2)
    assert part.load_torchvision(path) and not hasattr(part, "layer3") and part.fc is None
    assert torch.equal(part.layer2[1].conv2.weight, net.layer2[1].conv2.weight)
    x = torch.rand(1, 3, 32, 32)
    net.eval(), part.eval()
    assert torch.equal(part.features(x)[1], net.features(x)[1])


def test_target_rays_project_back_to_their_pixels():
    # A point at depth z on the ray of grid pixel (i, j), projected into the target camera
    # itself, lands on that pixel's centre; float32 round trip ~1e-6.
    k = torch.tensor([[[[0.8, 0, 0.45], [0, 0.9, 0.55], [0, 0, 1]]]])
    c2w = torch.eye(4)[None, None].clone()
    angle = torch.tensor(0.3)
    c2w[0, 0, :3, :3] = torch.tensor([[angle.cos(), 0, angle.sin()], [0, 1, 0],
                                      [-angle.sin(), 0, angle.cos()]])
    c2w[0, 0, :3, 3] = torch.tensor([0.2, -0.1, 0.5])
    origins, dirs = target_rays(c2w, k, (4, 5))
    points = origins[..., None, :] + dirs[..., None, :] * torch.tensor([0.5, 3.0])[:, None]
    xy, valid = project(points, c2w, k)
    ys, xs = torch.meshgrid((torch.arange(4) + 0.5) / 4, (torch.arange(5) + 0.5) / 5,
                            indexing="ij")
    expected = torch.stack([xs, ys], -1).view(-1, 1, 2).expand(-1, 2, 2)
    assert torch.allclose(xy[0, 0, 0], expected, atol=1e-5) and valid.all()
    # and the depth is the camera z: the point's z in the camera frame equals the sample
    cam = (torch.linalg.inv(c2w[0, 0]) @ torch.cat([points[0, 0].reshape(-1, 3),
                                                     torch.ones(40, 1)], 1).T)[2]
    assert torch.allclose(cam.view(20, 2), torch.tensor([0.5, 3.0]).expand(20, 2), atol=1e-5)


def test_highest_correlation_is_at_the_true_depth_on_a_mitsuba_scene():
    # Features replaced by a known texture (zero-mean 5x5 grey-level patches of the context
    # images), target = the frame between the contexts: on textured pixels the sample of
    # highest cross-view correlation should sit at Mitsuba's depth. Measured: 43% within one
    # sample step (96 samples, uniform in inverse depth over 0.2..20); chance is ~2%; errors
    # come from occlusion, repeated texture and the coarse step. A wrong convention (axes,
    # depth parameterisation, view order) drops it to chance.
    from usplat_dr.data.synth.render import TEXTURED, render_spec
    from usplat_dr.data.synth.scenes import make_spec

    spec = make_spec("indoor", 3, 12)
    frames = [4, 5, 6]
    images, depths, mats, intr = render_spec(spec, (64, 64), spp=16, seed=1, frames=frames)
    c2w = torch.tensor(np.asarray(spec["cameras"]["c2w"]), dtype=torch.float32)[frames]
    gray = torch.tensor(images, dtype=torch.float32).mean(-1)[:, None] / 255
    patch = F.unfold(F.pad(gray, (2, 2, 2, 2), mode="replicate"), 5).view(3, 25, 64, 64)
    patch = patch - patch.mean(1, keepdim=True)
    k = torch.tensor(intr, dtype=torch.float32)
    near, far = spec["near_far"]
    with torch.no_grad():
        _, aux = EpipolarProjection(96)(
            patch[[0, 2]][None], c2w[[0, 2]][None], k.expand(1, 2, 3, 3), c2w[[1]][None],
            k.expand(1, 1, 3, 3), torch.tensor([[near]]), torch.tensor([[far]]), (64, 64))
    best = aux["depths"][0, 0][aux["correlation"][0, 0].argmax(-1)]
    gt = torch.tensor(depths[1]).view(-1)
    seen = aux["valid"][0, 0].all(0).any(-1)  # some sample of the ray is seen by both views
    textured = torch.tensor(mats[1] == TEXTURED).view(-1) & torch.isfinite(gt) & seen
    step = (1 / near - 1 / far) / 95
    within = ((1 / best - 1 / gt).abs() <= step)[textured].float().mean().item()
    assert textured.sum() > 1000
    assert within > 0.3, within


def test_fusion_is_differentiable_and_finite_without_overlap():
    f = torch.rand(1, 2, 4, 16, 16, requires_grad=True)
    k = torch.tensor([[0.9, 0, 0.5], [0, 0.9, 0.5], [0, 0, 1.0]]).expand(1, 2, 3, 3)
    e = torch.eye(4).repeat(1, 2, 1, 1)
    e[0, 1, :3, :3] = torch.diag(torch.tensor([-1.0, 1, -1]))  # 180 degrees about y
    proj = EpipolarProjection(8)
    out, aux = proj(f, e, k, e[:, :1], k[:, :1], torch.ones(1, 1), 10 * torch.ones(1, 1),
                    (4, 4))
    assert torch.isfinite(out).all() and not aux["valid"][0, 0, 1].any()
    out.sum().backward()
    assert f.grad is not None and proj.log_temperature.grad is not None


def pinhole(c2w, k, x):
    """Normalised image coordinates and depth of world point ``x`` (float64, from P = K[R|t]
    written out: x_cam = R^T (x - o))."""
    r, o = c2w[:3, :3], c2w[:3, 3]
    cam = r.T @ (x - o)
    return (k @ (cam / cam[2]))[:2], cam[2]


def test_a_point_seen_by_both_contexts_is_sampled_at_its_pixels():
    # World point X seen by two context cameras and a rotated target camera. X's target
    # pixel is a grid-cell centre by construction of the target intrinsics; the ray of that
    # grid cell at X's target depth must be X, and projecting it into each context view must
    # give X's pixel there (independent float64 pinhole above; 1e-5: float32 Proj path).
    x = torch.tensor([0.3, -0.2, 4.0], dtype=torch.float64)
    k = torch.tensor([[0.9, 0, 0.5], [0, 0.8, 0.5], [0, 0, 1]], dtype=torch.float64)

    def cam(yaw, origin):
        c2w = torch.eye(4, dtype=torch.float64)
        c, s = math.cos(yaw), math.sin(yaw)
        c2w[:3, :3] = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)
        c2w[:3, 3] = torch.tensor(origin, dtype=torch.float64)
        return c2w

    contexts = torch.stack([cam(0.05, [-0.4, 0, 0]), cam(-0.05, [0.4, 0.1, 0])])
    target = cam(0.2, [0.1, -0.05, 0.3])
    grid = (4, 6)
    uv, z = pinhole(target, k, x)
    cell = torch.tensor([(3 + 0.5) / grid[1], (1 + 0.5) / grid[0]], dtype=torch.float64)
    kt = k.clone()
    kt[:2, 2] += cell - uv  # shift the principal point: X's pixel is the centre of cell (1, 3)
    origins, dirs = target_rays(target[None, None].float(), kt[None, None].float(), grid)
    point = origins[0, 0, 0] + dirs[0, 0, 1 * grid[1] + 3] * z.float()
    assert torch.allclose(point.double(), x, atol=1e-5)
    xy, valid = project(point.view(1, 1, 1, 1, 3), contexts[None].float(),
                        k[None].expand(1, 2, 3, 3).float())
    for v in range(2):
        expected, _ = pinhole(contexts[v], k, x)
        assert torch.allclose(xy[0, 0, v, 0, 0].double(), expected, atol=1e-5)
        assert valid[0, 0, v, 0, 0]


def proj_loop(features, extrinsics, intrinsics, t_extrinsics, t_intrinsics, t_near, t_far,
              grid, num, temperature):
    """Proj written as explicit float64 loops from its definition (usplat_dr's
    model/hypernet/epipolar.py docstring): per target pixel centre, ``num`` depths uniform in
    inverse depth from far to near on the ray with camera depth z; each sample projected into
    every context view (invalid behind the camera or outside [0, 1]^2), features sampled
    bilinearly (pixel centres at (i + 0.5) / size, zeros outside); correlation = mean over
    the valid view pairs of the cosine similarity; softmax over the ray's samples of
    temperature * correlation (-1e4 where no view sees the sample); the fused feature is
    the weighted sum over samples of the mean feature of the views that see it."""
    f = features.double().numpy()
    b, v, c, h, w = f.shape
    n = t_intrinsics.shape[1]
    gh, gw = grid
    out = np.zeros((b, n, c, gh, gw))

    def bilinear(fmap, x, y):
        px, py = x * w - 0.5, y * h - 0.5
        x0, y0 = math.floor(px), math.floor(py)
        acc = np.zeros(c)
        for yy, wy in ((y0, 1 - (py - y0)), (y0 + 1, py - y0)):
            for xx, wx in ((x0, 1 - (px - x0)), (x0 + 1, px - x0)):
                if 0 <= xx < w and 0 <= yy < h:
                    acc += wy * wx * fmap[:, yy, xx]
        return acc

    for bi in range(b):
        for ni in range(n):
            k_t = t_intrinsics[bi, ni].double().numpy()
            c2w = t_extrinsics[bi, ni].double().numpy()
            near, far = float(t_near[bi, ni]), float(t_far[bi, ni])
            depths = [1 / (1 / far + s / (num - 1) * (1 / near - 1 / far)) for s in range(num)]
            for i in range(gh):
                for j in range(gw):
                    ray = c2w[:3, :3] @ np.linalg.solve(k_t, [(j + 0.5) / gw, (i + 0.5) / gh,
                                                              1.0])
                    corr, feats, seen = [], [], []
                    for z in depths:
                        point = c2w[:3, 3] + z * ray
                        vals, ok = [], []
                        for vi in range(v):
                            w2c = np.linalg.inv(extrinsics[bi, vi].double().numpy())
                            pc = w2c[:3, :3] @ point + w2c[:3, 3]
                            uv = (intrinsics[bi, vi].double().numpy() @ (pc / pc[2]))[:2]
                            ok.append(pc[2] > 1e-6 and (0 <= uv).all() and (uv <= 1).all())
                            vals.append(bilinear(f[bi, vi], *uv) if ok[-1] else np.zeros(c))
                        pairs = [(p, q) for p in range(v) for q in range(p + 1, v)
                                 if ok[p] and ok[q]]
                        cos = [vals[p] @ vals[q] / np.sqrt((vals[p] @ vals[p]) *
                                                           (vals[q] @ vals[q]) + 1e-24)
                               for p, q in pairs]
                        corr.append(np.mean(cos) if cos else 0.0)
                        feats.append(sum(x for x, o in zip(vals, ok) if o) / max(sum(ok), 1))
                        seen.append(any(ok))
                    logits = np.where(seen, temperature * np.array(corr), -1e4)
                    wts = np.exp(logits - logits.max())
                    wts /= wts.sum()
                    out[bi, ni, :, i, j] = sum(wt * ft for wt, ft in zip(wts, feats))
    return out


def test_proj_fuses_three_context_views_as_its_definition_says():
    from usplat_dr.render.scenes import orbit_cameras

    gen = torch.Generator().manual_seed(5)
    c2w = orbit_cameras(5, radius=3.0, height=0.4, arc_degrees=60.0).double()
    context, target = c2w[[0, 2, 4]][None], c2w[[1, 3]][None]
    k = torch.tensor([[0.9, 0.0, 0.48], [0.0, 0.95, 0.52], [0.0, 0.0, 1.0]], dtype=torch.float64)
    features = torch.randn(1, 3, 4, 6, 7, generator=gen, dtype=torch.float64)
    near, far = torch.full((1, 2), 1.0, dtype=torch.float64), torch.full((1, 2), 6.0,
                                                                         dtype=torch.float64)
    proj = EpipolarProjection(num_samples=5, temperature=10.0).double()
    ours, aux = proj(features, context, k.expand(1, 3, 3, 3), target, k.expand(1, 2, 3, 3),
                     near, far, (3, 4))
    temperature = proj.log_temperature.exp().item()  # 10 after a float32 log round trip
    ref = proj_loop(features, context, k.expand(1, 3, 3, 3), target, k.expand(1, 2, 3, 3),
                    near, far, (3, 4), 5, temperature)
    # both float64; the module's batched reductions differ from the loops' order: ~1e-12
    assert np.allclose(ours.detach().numpy(), ref, atol=1e-10)
    # the case is not degenerate: some samples are seen by all three views, some by fewer
    seen_by = aux["valid"].sum(2)
    assert (seen_by == 3).any() and ((seen_by > 0) & (seen_by < 3)).any()
