"""The ``baseline`` gauge (``UniqueSplatCfg.gauge``): the model in it equals the world-gauge
model run on the scene divided by its context baseline by hand (the reference), its prediction
scales with the world (means, covariances, depths) and its renders do not change, where the
world-gauge model's do; coincident context cameras are refused by name."""

import logging

import pytest
import torch

from tests.model.conftest import two_view_cameras
from usplat_dr.data.types import SceneInputs
from usplat_dr.model import UniqueSplat
from usplat_dr.model.uniquesplat import UniqueSplatCfg


@pytest.fixture(autouse=True)
def _quiet_resnet(caplog):
    caplog.set_level(logging.ERROR, logger="usplat_dr.model.hypernet.resnet")


def tiny(gauge: str) -> UniqueSplat:
    """A tiny (c) with an open view-specific branch (``delta_init_std``), so that the target
    cameras reach the weights too; the same weights for every gauge (seeded)."""
    torch.manual_seed(0)
    return UniqueSplat.from_preset("tiny", variant="full", gauge=gauge,
                                   delta_init_std=0.05).eval()


def scene(k: float = 1.0, size: int = 32) -> SceneInputs:
    """Two context cameras 0.3 apart (one rotated a little), two targets, near/far 0.5/20, in
    a world scaled by ``k`` about its origin (which is not on any camera)."""
    g = torch.Generator().manual_seed(3)
    e, intr = two_view_cameras(1, 2, baseline=0.3)
    c, s = torch.cos(torch.tensor(0.1)), torch.sin(torch.tensor(0.1))
    e[0, 1, :3, :3] = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    e[..., :3, 3] += torch.tensor([0.4, -0.2, 1.0])
    te = e[:, :1].repeat(1, 2, 1, 1)
    te[0, :, 0, 3] += torch.tensor([0.1, 0.45])
    te[0, :, 1, 3] += 0.05
    for m in (e, te):
        m[..., :3, 3] *= k
    return SceneInputs.of(images=torch.rand(1, 2, 3, size, size, generator=g), extrinsics=e,
                          intrinsics=intr, near=torch.full((1, 2), 0.5 * k),
                          far=torch.full((1, 2), 20.0 * k), target_extrinsics=te,
                          target_intrinsics=intr[:, :1].repeat(1, 2, 1, 1),
                          target_near=torch.full((1, 2), 0.5 * k),
                          target_far=torch.full((1, 2), 20.0 * k))


def divided(args: SceneInputs, s: float) -> SceneInputs:
    """``args`` with every translation and bound divided by ``s``, by hand."""
    e, te = args.extrinsics.clone(), args.target_extrinsics.clone()
    e[..., :3, 3] /= s
    te[..., :3, 3] /= s
    return args.replaced(extrinsics=e, target_extrinsics=te, near=args.near / s,
                         far=args.far / s, target_near=args.target_near / s,
                         target_far=args.target_far / s)


def test_the_baseline_gauge_is_the_world_model_on_the_scene_divided_by_its_baseline():
    args = scene()
    s = float((args.extrinsics[0, 0, :3, 3] - args.extrinsics[0, 1, :3, 3]).norm())
    with torch.no_grad():
        got = tiny("baseline")(*args, render=False)
        ref = tiny("world")(*divided(args, s), render=False)
    # The same network on inputs that differ by float32 rounding of the division (1 ulp of
    # the translations and bounds) and of the scaling back: measured 8e-6 of the largest
    # value for the means, 1.2e-5 for the covariances and 1e-6 for the rest (2026-12-03); the
    # bound, 5e-5 of the largest value, is 40 float32 ulps carried through the network.
    g, r = got.gaussians, ref.gaussians
    for name, power in (("means", 1), ("covariances", 2), ("scales", 1), ("harmonics", 0),
                        ("opacities", 0), ("rotations", 0)):
        close(getattr(g, name), getattr(r, name) * s ** power, name)
    close(got.aux["context_depths"], ref.aux["context_depths"] * s, "context_depths")


def close(a: torch.Tensor, b: torch.Tensor, name: str, rel: float = 5e-5) -> None:
    err = float((a - b).abs().max())
    assert err <= rel * float(b.abs().max()), (name, err, float(b.abs().max()))


@pytest.mark.parametrize("k", [0.05, 7.3])
def test_a_baseline_gauge_prediction_scales_with_the_world_and_renders_the_same(k):
    model = tiny("baseline")
    with torch.no_grad():
        a = model(*scene(1.0))
        b = model(*scene(k))
    # Inputs equal after the gauge up to float32 rounding of k (translations and bounds):
    # the Gaussians to 5e-5 of their largest value (as above), the renders (in [0, 1]) to
    # 1e-4.
    close(b.gaussians.means, a.gaussians.means * k, "means")
    close(b.gaussians.opacities, a.gaussians.opacities, "opacities")
    close(b.depth, a.depth * k, "depth")
    assert (b.color - a.color).abs().max() < 1e-4


def test_the_world_gauge_does_not_scale_so_the_test_above_can_fail():
    # MVSplat's depth head refines absolute inverse depths: the same scene in another unit is
    # another prediction (measured on the shipped models: a scene 3x larger costs them 7 dB).
    model = tiny("world")
    with torch.no_grad():
        a = model(*scene(1.0), render=False)
        b = model(*scene(7.3), render=False)
    assert (b.gaussians.opacities - a.gaussians.opacities).abs().max() > 1e-3
    assert not torch.allclose(b.gaussians.means, a.gaussians.means * 7.3, rtol=1e-3)


def test_coincident_context_cameras_are_refused_in_the_baseline_gauge():
    args = scene()
    e = args.extrinsics.clone()
    e[:, 1, :3, 3] = e[:, 0, :3, 3]
    with torch.no_grad(), pytest.raises(ValueError, match="share a centre"):
        tiny("baseline")(*args.replaced(extrinsics=e), render=False)


def test_the_gauge_is_checked_and_kept_in_the_config():
    with pytest.raises(ValueError, match="gauge must be one of"):
        UniqueSplatCfg(gauge="metres")
    cfg = UniqueSplatCfg(gauge="baseline")
    assert UniqueSplatCfg.from_dict(cfg.to_dict()).gauge == "baseline"
    assert UniqueSplatCfg().gauge == "world"  # MVSplat's checkpoints load as before
