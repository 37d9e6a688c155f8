"""The typed crossing from data to model: what a dataset yields (``Views``, ``Example``) and
what ``UniqueSplat`` takes (``SceneInputs``, made from a batch by ``model_inputs``).

Shapes: ``V`` context views, ``N`` target views, ``B`` examples in a batch (a batch is the
``default_collate`` of examples: every tensor gains a leading ``B``).
"""

from typing import NamedTuple, TypedDict

import torch
from jaxtyping import Float
from torch import Tensor


class Views(TypedDict, total=False):
    """One side (context or target) of an example; see ``usplat_dr.data.shims``."""

    extrinsics: Float[Tensor, "view 4 4"]  # camera-to-world, OpenCV axes
    intrinsics: Float[Tensor, "view 3 3"]  # normalised by image width (row 0) and height (row 1)
    image: Float[Tensor, "view 3 h w"]  # in [0, 1]
    near: Float[Tensor, " view"]
    far: Float[Tensor, " view"]
    index: Tensor  # frame numbers [view]
    depth: Float[Tensor, "view h w"]  # camera-space z, +inf on a miss (synthetic sets only)


class Example(TypedDict):
    """What ``ChunkDataset`` yields: the context and target views of one scene."""

    context: Views
    target: Views
    scene: str


class SceneInputs(NamedTuple):
    """``UniqueSplat``'s inputs, in the order of its ``forward``: ``model(*inputs)``.
    Extrinsics before intrinsics, as everywhere; read the fields by name, not by position."""

    images: Float[Tensor, "b v 3 h w"]
    extrinsics: Float[Tensor, "b v 4 4"]
    intrinsics: Float[Tensor, "b v 3 3"]
    near: Float[Tensor, "b v"]
    far: Float[Tensor, "b v"]
    target_extrinsics: Float[Tensor, "b n 4 4"]
    target_intrinsics: Float[Tensor, "b n 3 3"]
    target_near: Float[Tensor, "b n"]
    target_far: Float[Tensor, "b n"]


def model_inputs(batch: dict, device: torch.device | str = "cpu") -> SceneInputs:
    """The model's inputs from a batch of examples, on ``device``.

    Examples:
        >>> v = {"image": torch.zeros(1, 2, 3, 8, 8), "intrinsics": torch.eye(3).expand(1, 2, 3, 3),
        ...      "extrinsics": torch.eye(4).expand(1, 2, 4, 4), "near": torch.ones(1, 2),
        ...      "far": torch.full((1, 2), 9.0)}
        >>> inputs = model_inputs({"context": v, "target": v})
        >>> inputs.target_intrinsics.shape
        torch.Size([1, 2, 3, 3])
    """
    c, t = batch["context"], batch["target"]
    return SceneInputs(
        images=c["image"].to(device), extrinsics=c["extrinsics"].to(device),
        intrinsics=c["intrinsics"].to(device), near=c["near"].to(device),
        far=c["far"].to(device), target_extrinsics=t["extrinsics"].to(device),
        target_intrinsics=t["intrinsics"].to(device), target_near=t["near"].to(device),
        target_far=t["far"].to(device))
