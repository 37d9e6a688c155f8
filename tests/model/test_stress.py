"""Numerical stress for the whole pipeline (UniqueSplat (c), tiny preset, rendered): each
case gives finite Gaussians and finite renders, or a clear error naming the argument; never
NaN renders or a crash deep in a kernel."""

import logging
import math

import pytest
import torch

from usplat_dr.data.types import SceneInputs
from usplat_dr.model import UniqueSplat


@pytest.fixture(scope="module")
def model():
    logging.getLogger("usplat_dr.model.hypernet.resnet").setLevel(logging.ERROR)
    torch.manual_seed(0)
    return UniqueSplat.from_preset("tiny", variant="full").eval()


def scene(scale=1.0, baseline=0.1, fx=0.85, images=None, target_shift=0.05, rot=0.0,
          target_near=1.0):
    k = torch.tensor([[fx, 0, 0.5], [0, fx, 0.5], [0, 0, 1]]).repeat(1, 2, 1, 1)
    e = torch.eye(4).repeat(1, 2, 1, 1)
    e[0, 1, 0, 3] = baseline * scale
    if rot:
        c, s = math.cos(rot), math.sin(rot)
        e[0, 1, :3, :3] = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    te = torch.eye(4)[None, None].clone()
    te[0, 0, 0, 3] = target_shift * scale
    g = torch.Generator().manual_seed(1)
    x = torch.rand(1, 2, 3, 32, 32, generator=g) if images is None else images
    ones2, ones1 = torch.ones(1, 2), torch.ones(1, 1)
    return SceneInputs.of(images=x, extrinsics=e, intrinsics=k, near=scale * ones2,
                       far=100 * scale * ones2, target_extrinsics=te,
                       target_intrinsics=k[:, :1].clone(), target_near=target_near * scale * ones1,
                       target_far=100 * scale * ones1)


CASES = {
    "identical context cameras (zero baseline)": dict(baseline=0.0),
    "context views that do not overlap (180 degrees apart)": dict(rot=math.pi),
    "field of view near 0 degrees": dict(fx=1e4),
    "field of view near 180 degrees": dict(fx=1e-3),
    "constant-colour images": dict(images=torch.full((1, 2, 3, 32, 32), 0.5)),
    "scene scaled by 1e-3": dict(scale=1e-3),
    "scene scaled by 1e3": dict(scale=1e3),
    "target camera at a context camera": dict(target_shift=0.0),
    "target near plane inside the scene": dict(target_near=20.0),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_stress_case_is_finite(model, case):
    with torch.no_grad():
        out = model(*scene(**CASES[case]))
    g = out.gaussians
    for name in ("means", "covariances", "harmonics", "opacities"):
        assert torch.isfinite(getattr(g, name)).all(), name
    for name in ("color", "alpha", "depth"):
        assert torch.isfinite(getattr(out, name)).all(), name
    assert ((out.alpha >= 0) & (out.alpha <= 1)).all()


def test_bad_values_are_clear_errors(model):
    args = scene()
    nan_image = args.images.clone()
    nan_image[0, 1, 2, 3, 4] = float("nan")
    with pytest.raises(ValueError, match="images holds 1 NaN"):
        model(*args.replaced(images=nan_image))
    with pytest.raises(ValueError, match="near must be > 0"):
        model(*args.replaced(near=torch.zeros(1, 2)))
    te = args.target_extrinsics.clone()
    te[0, 0, 1, 3] = float("inf")
    with pytest.raises(ValueError, match="target_extrinsics holds 1 NaN or Inf"):
        model(*args.replaced(target_extrinsics=te))
    with pytest.raises(ValueError, match="target_far > target_near"):  # target far < near
        model(*args.replaced(target_far=torch.full((1, 1), 0.5)))
