"""The crossing from data to model: ``SceneInputs`` is in the order of ``UniqueSplat.forward``
(so ``model(*inputs)`` passes each tensor where it belongs), and ``model_inputs`` fills each
field from the batch entry of its name. Cameras are (extrinsics, intrinsics) at every seam."""

import inspect

import torch

from usplat_dr.data.types import SceneInputs, model_inputs
from usplat_dr.model import PrimaryNetwork, UniqueSplat


def parameters(fn) -> list[str]:
    return [p for p in inspect.signature(fn).parameters if p != "self"]


def test_scene_inputs_are_in_the_order_of_forwards_parameters():
    assert list(SceneInputs._fields) == parameters(UniqueSplat.forward)[:3]
    # the context half, as loose tensors: what the encoders take first
    for fn in (UniqueSplat.encode, PrimaryNetwork.forward, PrimaryNetwork.encode):
        assert parameters(fn)[:5] == ["images", *SceneInputs.FLAT[:4]], fn.__qualname__
    assert SceneInputs.FLAT.index("extrinsics") < SceneInputs.FLAT.index("intrinsics")


def test_model_inputs_fills_each_field_from_its_namesake():
    def views(n: int, offset: float) -> dict:
        # every tensor different, so that a field filled from another entry shows
        return {"image": torch.full((1, n, 3, 8, 8), offset),
                "extrinsics": torch.eye(4).repeat(1, n, 1, 1) + offset + 1,
                "intrinsics": torch.eye(3).repeat(1, n, 1, 1) + offset + 2,
                "near": torch.full((1, n), offset + 3), "far": torch.full((1, n), offset + 4)}

    context, target = views(2, 0.0), views(3, 10.0)
    inputs = model_inputs({"context": context, "target": target})
    for side, prefix in ((context, ""), (target, "target_")):
        for key in ("extrinsics", "intrinsics", "near", "far"):
            assert torch.equal(getattr(inputs, prefix + key), side[key]), prefix + key
    assert torch.equal(inputs.images, context["image"])
