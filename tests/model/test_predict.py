"""``UniqueSplat.predict``: images and cameras as users hold them in, the Gaussians, colour and
depth of each target out; the same numbers as ``forward`` on the same inputs."""

import numpy as np
import pytest
import torch

from tests.model.conftest import two_view_cameras
from usplat_dr.geometry.cameras import Cameras
from usplat_dr.model import UniqueSplat


def users_scene(n: int = 5):
    """uint8 images channels-last (as files load), normalised cameras, n targets."""
    g = torch.Generator().manual_seed(0)
    e, k = two_view_cameras(1, 2)
    te = torch.eye(4).repeat(n, 1, 1)
    te[:, 0, 3] = torch.linspace(-0.05, 0.15, n)
    images = (torch.rand(2, 64, 64, 3, generator=g) * 255).to(torch.uint8).numpy()
    return images, k[0], e[0], k[0, :1].expand(n, 3, 3).clone(), te


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return UniqueSplat.from_preset("tiny", variant="full", delta_init_std=1e-2).eval()


def test_predict_is_forward_on_the_same_inputs(model):
    images, k, e, tk, te = users_scene()
    pred = model.predict(images, intrinsics=k, extrinsics=e, target_intrinsics=tk,
                         target_extrinsics=te, near=1.0, far=100.0, chunk=5)
    x = torch.from_numpy(images).permute(0, 3, 1, 2).float()[None] / 255
    with torch.no_grad():
        out = model(x, Cameras(e[None], k[None], torch.ones(1, 2), torch.full((1, 2), 100.0)),
                    Cameras(te[None], tk[None], torch.ones(1, 5), torch.full((1, 5), 100.0)))
    # the same arithmetic on the same tensors: bit-for-bit
    assert torch.equal(pred.color, out.color[0].clamp(0, 1))
    assert torch.equal(pred.alpha, out.alpha[0])
    assert torch.equal(pred.depth, out.depth[0] / out.alpha[0].clamp(min=1e-3))
    assert len(pred.gaussians) == 5
    assert torch.equal(pred.gaussians[3].means, out.target(0, 3).means)
    # (c): each target its own Gaussians
    assert not torch.equal(pred.gaussians[0].harmonics, pred.gaussians[4].harmonics)


def test_chunks_and_input_forms_do_not_change_the_views(model):
    images, k, e, tk, te = users_scene()
    ref = model.predict(images, intrinsics=k, extrinsics=e, target_intrinsics=tk,
                        target_extrinsics=te, chunk=5)
    floats = torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255  # [V, 3, H, W]
    again = model.predict(list(floats), intrinsics=k.numpy(), extrinsics=e.numpy(),
                          target_intrinsics=tk, target_extrinsics=te, chunk=2)
    # targets are independent; batching 2 instead of 5 changes only the convolutions' float
    # rounding: ~1e-7 alone, 1e-4 on a few pixels after the evaluation tests ran (near-equal
    # depths swap places in the depth sort under such rounding, thread counts differing);
    # a wrong camera or view moves colours by > 1e-2, so 1e-3 still tells them apart
    assert (again.color - ref.color).abs().max() < 1e-3
    one = model.predict(images, intrinsics=k, extrinsics=e, target_intrinsics=tk[2],
                        target_extrinsics=te[2])  # a single camera, unbatched
    assert one.color.shape == (1, 3, 64, 64)
    assert (one.color[0] - ref.color[2]).abs().max() < 1e-3  # (as above)
    assert model.training is False


@pytest.mark.parametrize(("change", "needle"), [
    ({"intrinsics": "pixels"}, "intrinsics must be normalised"),
    ({"target_intrinsics": "pixels"}, "target_intrinsics must be normalised"),
    ({"extrinsics": "3x3"}, r"extrinsics must have shape \[N, 4, 4\]"),
    ({"intrinsics": "one"}, r"intrinsics must hold one camera per image \(2\)"),
    ({"target_extrinsics": "two"}, "target_extrinsics and target_intrinsics must hold as many"),
    ({"images": "range"}, r"images must be uint8 \(0-255\) or float in \[0, 1\]"),
    ({"images": "shape"}, "images must be V images"),
    ({"near": -1.0}, "near must be a positive number"),
    ({"far": 0.5}, "far must exceed near"),
    # UserViews.near of a transforms.json (no sparse points) passed on as it is
    ({"near": None}, r"near= is None: pass the depth range in scene units \(near=, far=\)"),
    ({"far": None}, r"far= is None"),
    ({"chunk": 0}, "chunk must be an int >= 1"),
])
def test_wrong_inputs_name_the_argument(model, change, needle):
    images, k, e, tk, te = users_scene(3)
    kw = dict(intrinsics=k, extrinsics=e, target_intrinsics=tk, target_extrinsics=te)
    key, what = next(iter(change.items()))
    if what == "pixels":
        kw[key] = kw[key] * torch.tensor([[64.0], [64.0], [1.0]])
    elif what == "3x3":
        kw[key] = kw[key][:, :3, :3]
    elif what == "one":
        kw[key] = kw[key][:1]
    elif what == "two":
        kw[key] = kw[key][:2]
    elif what == "range":
        images = images.astype(np.float32)
    elif what == "shape":
        images = images[0]
    else:
        kw[key] = what
    with pytest.raises(ValueError, match=needle):
        model.predict(images, **kw)
