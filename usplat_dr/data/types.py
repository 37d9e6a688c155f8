"""The typed crossing from data to model: what a dataset yields (``Views``, ``Example``) and
what ``UniqueSplat`` takes (``SceneInputs``, made from a batch by ``model_inputs``).

Shapes: ``V`` context views, ``N`` target views, ``B`` examples in a batch (a batch is the
``default_collate`` of examples: every tensor gains a leading ``B``).
"""

from typing import NamedTuple, TypedDict

import torch
from jaxtyping import Float
from torch import Tensor

from usplat_dr.geometry.cameras import Cameras


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
    """``UniqueSplat``'s inputs, in the order of its ``forward``: ``model(*inputs)``: the
    context ``images`` and two ``Cameras``, the ``context`` views' and the ``targets``'. The
    cameras' fields read through as ``inputs.near``, ``inputs.target_extrinsics``... too."""

    images: Float[Tensor, "b v 3 h w"]
    context: Cameras
    targets: Cameras

    #: The flat names of the cameras' fields, context then targets (``of``, ``replaced``).
    FLAT = ("extrinsics", "intrinsics", "near", "far", "target_extrinsics",
            "target_intrinsics", "target_near", "target_far")

    @staticmethod
    def of(images: Float[Tensor, "b v 3 h w"], extrinsics: Float[Tensor, "b v 4 4"],
           intrinsics: Float[Tensor, "b v 3 3"], near: Float[Tensor, "b v"],
           far: Float[Tensor, "b v"], target_extrinsics: Float[Tensor, "b n 4 4"],
           target_intrinsics: Float[Tensor, "b n 3 3"], target_near: Float[Tensor, "b n"],
           target_far: Float[Tensor, "b n"]) -> "SceneInputs":
        """The inputs of these tensors (the cameras' fields as loose tensors)."""
        return SceneInputs(images, Cameras(extrinsics, intrinsics, near, far),
                           Cameras(target_extrinsics, target_intrinsics, target_near,
                                   target_far))

    def replaced(self, **fields: Tensor) -> "SceneInputs":
        """A copy with some fields replaced, by their flat names (``images``, ``near``,
        ``target_extrinsics``...)."""
        unknown = set(fields) - {"images", *SceneInputs.FLAT}
        if unknown:
            raise TypeError(f"SceneInputs has no field(s) {sorted(unknown)}")
        now = {"images": self.images, **{k: getattr(self, k) for k in SceneInputs.FLAT}}
        return SceneInputs.of(**{**now, **fields})

    def to(self, device: torch.device | str) -> "SceneInputs":
        """The same inputs on ``device``."""
        return SceneInputs(self.images.to(device), self.context.to(device),
                           self.targets.to(device))

    @property
    def extrinsics(self) -> Float[Tensor, "b v 4 4"]:
        return self.context.extrinsics

    @property
    def intrinsics(self) -> Float[Tensor, "b v 3 3"]:
        return self.context.intrinsics

    @property
    def near(self) -> Float[Tensor, "b v"]:
        return self.context.near

    @property
    def far(self) -> Float[Tensor, "b v"]:
        return self.context.far

    @property
    def target_extrinsics(self) -> Float[Tensor, "b n 4 4"]:
        return self.targets.extrinsics

    @property
    def target_intrinsics(self) -> Float[Tensor, "b n 3 3"]:
        return self.targets.intrinsics

    @property
    def target_near(self) -> Float[Tensor, "b n"]:
        return self.targets.near

    @property
    def target_far(self) -> Float[Tensor, "b n"]:
        return self.targets.far


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

    def cameras(side: dict) -> Cameras:
        return Cameras(side["extrinsics"].to(device), side["intrinsics"].to(device),
                       side["near"].to(device), side["far"].to(device))

    return SceneInputs(images=c["image"].to(device), context=cameras(c), targets=cameras(t))
