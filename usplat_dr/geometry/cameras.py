"""Camera conventions, written once.

- Extrinsics are camera-to-world (``c2w``) 4x4 matrices with OpenCV axes: +X right, +Y down,
  +Z forward (the data convention of pixelSplat/MVSplat).
- ``intrinsics`` are normalised: row 0 divided by the image width, row 1 by the height, so
  ``[[fx/W, 0, cx/W], [0, fy/H, cy/H], [0, 0, 1]]``; ``Ks`` are in pixels.
- A pixel (row i, column j) is sampled at (j + 0.5, i + 0.5) in pixel units.
- Mitsuba's perspective sensor looks along its local +Z with local +X pointing to the image's
  left and +Y up. So Mitsuba's ``to_world`` is the OpenCV c2w with its X and Y axes negated:
  ``to_world = c2w @ diag(-1, -1, 1, 1)`` (``opencv_c2w_to_mitsuba``; the inverse is the
  same product). Tests project known points both ways (``tests/data/test_conventions.py``).
"""

from dataclasses import dataclass

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor


@dataclass(frozen=True)
class Cameras:
    """A batch of cameras as one value: ``extrinsics`` [B, N, 4, 4] (camera-to-world, OpenCV
    axes), ``intrinsics`` [B, N, 3, 3] (normalised), ``near`` and ``far`` [B, N] (scene units),
    the conventions above. ``UniqueSplat.forward`` takes the context views' and the targets'.

    Examples:
        >>> cams = Cameras(torch.eye(4).expand(1, 2, 4, 4), torch.eye(3).expand(1, 2, 3, 3),
        ...                torch.ones(1, 2), torch.full((1, 2), 100.0))
        >>> cams.count, cams.to("cpu").far.tolist()
        (2, [[100.0, 100.0]])
    """

    extrinsics: Float[Tensor, "b n 4 4"]
    intrinsics: Float[Tensor, "b n 3 3"]
    near: Float[Tensor, "b n"]
    far: Float[Tensor, "b n"]

    @property
    def count(self) -> int:
        """N: cameras per example."""
        return self.extrinsics.shape[1]

    def to(self, device: torch.device | str) -> "Cameras":
        """The same cameras on ``device``."""
        return Cameras(*(t.to(device) for t in (self.extrinsics, self.intrinsics, self.near,
                                               self.far)))

    def scaled(self, factor: Float[Tensor, " b"]) -> "Cameras":
        """The same cameras in a world scaled by ``factor`` (one per example) about its
        origin: the centres and near/far multiplied, the rotations and intrinsics kept.

        Examples:
            >>> cams = Cameras(torch.eye(4).expand(1, 2, 4, 4).clone(),
            ...                torch.eye(3).expand(1, 2, 3, 3), torch.ones(1, 2),
            ...                torch.full((1, 2), 100.0))
            >>> cams.extrinsics[0, 1, 0, 3] = 2.0
            >>> half = cams.scaled(torch.tensor([0.5]))
            >>> half.extrinsics[0, 1, 0, 3].item(), half.near.tolist(), half.far.tolist()
            (1.0, [[0.5, 0.5]], [[50.0, 50.0]])
        """
        extrinsics, near, far = scale_world(self.extrinsics, self.near, self.far, factor)
        return Cameras(extrinsics, self.intrinsics, near, far)


def scale_world(extrinsics: Float[Tensor, "b n 4 4"], near: Float[Tensor, "b n"] | None,
                far: Float[Tensor, "b n"] | None, factor: Float[Tensor, " b"]) -> tuple:
    """Camera-to-world matrices and bounds in a world scaled by ``factor`` (one per example)
    about its origin: ``(extrinsics, near, far)`` with the centres and bounds multiplied
    (``None`` bounds stay ``None``)."""
    f = factor.to(extrinsics.dtype)
    out = extrinsics.clone()
    out[..., :3, 3] = out[..., :3, 3] * f[:, None, None]
    return (out, *(None if t is None else t * f[:, None].to(t.dtype) for t in (near, far)))


def baseline_scale(extrinsics: Float[Tensor, "b v 4 4"]) -> Float[Tensor, " b"]:
    """The distance between the first and the last context camera of each example: the unit of
    the ``baseline`` gauge (pixelSplat's ``make_baseline_1``). Raises ``ValueError`` naming the
    examples whose context cameras share a centre (no baseline, no scale to read)."""
    scale = (extrinsics[:, 0, :3, 3] - extrinsics[:, -1, :3, 3]).norm(dim=-1)
    bad = (~torch.isfinite(scale) | (scale < 1e-6)).nonzero().flatten().tolist()
    if bad:
        raise ValueError(f"the context cameras of example(s) {bad} share a centre (baseline "
                         f"{scale[bad[0]].item():.2g}): a model in the 'baseline' gauge needs "
                         f"two context views taken from different places")
    return scale


def look_at(
    eye: Float[Tensor, "*batch 3"],
    target: Float[Tensor, "*batch 3"],
    up: Float[Tensor, "*batch 3"],
) -> Float[Tensor, "*batch 4 4"]:
    """OpenCV camera-to-world matrices looking from ``eye`` at ``target``; ``up`` is world up
    (the camera's -Y axis points as close to it as possible).

    Examples:
        >>> c2w = look_at(torch.tensor([0.0, 0, -2]), torch.zeros(3), torch.tensor([0.0, -1, 0]))
        >>> c2w[:3, 2].tolist()  # +Z (forward) points from the eye to the target
        [0.0, 0.0, 1.0]
    """
    forward = torch.nn.functional.normalize(target - eye, dim=-1)  # +Z
    # +X = (+Y) x (+Z) with +Y (down) close to -up, so that the frame is right-handed.
    right = torch.nn.functional.normalize(torch.linalg.cross(-up, forward, dim=-1), dim=-1)
    down = torch.linalg.cross(forward, right, dim=-1)  # +Y
    c2w = torch.zeros(*eye.shape[:-1], 4, 4, dtype=eye.dtype, device=eye.device)
    c2w[..., :3, 0] = right
    c2w[..., :3, 1] = down
    c2w[..., :3, 2] = forward
    c2w[..., :3, 3] = eye
    c2w[..., 3, 3] = 1.0
    return c2w


def pixel_centres(h: int, w: int, device=None, dtype=torch.float32) -> Float[Tensor, "hw 2"]:
    """Normalised image coordinates ((x + 0.5) / w, (y + 0.5) / h) of the pixel centres of an
    h x w grid, raster order (pixelSplat's ``sample_image_grid``).

    Examples:
        >>> pixel_centres(1, 2).tolist()
        [[0.25, 0.5], [0.75, 0.5]]
    """
    ys, xs = torch.meshgrid((torch.arange(h, device=device, dtype=dtype) + 0.5) / h,
                            (torch.arange(w, device=device, dtype=dtype) + 0.5) / w,
                            indexing="ij")
    return torch.stack([xs, ys], dim=-1).view(-1, 2)


def normalized_intrinsics(
    fx: float, fy: float, cx: float = 0.5, cy: float = 0.5, batch: tuple[int, ...] = ()
) -> Float[Tensor, "*batch 3 3"]:
    """Normalised intrinsics (fx, cx in units of the image width; fy, cy of its height)."""
    k = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return k.expand(*batch, 3, 3).clone()


def pixel_directions(intrinsics: np.ndarray, image_shape: tuple[int, int]) -> np.ndarray:
    """[H, W, 3] camera-space ray directions ``(x', y', 1)`` through every pixel centre, for
    normalised ``intrinsics`` [3, 3] (numpy). A point at camera-space depth z on the ray of
    pixel (i, j) is ``z * directions[i, j]``.

    Examples:
        >>> k = np.array([[0.5, 0, 0.5], [0, 0.5, 0.5], [0, 0, 1]])
        >>> pixel_directions(k, (2, 2))[0, 0].tolist()  # pixel centre (0.5, 0.5) of 2x2
        [-0.5, -0.5, 1.0]
    """
    h, w = image_shape
    k = np.asarray(intrinsics, dtype=np.float64)
    x = ((np.arange(w) + 0.5) / w - k[0, 2]) / k[0, 0]
    y = ((np.arange(h) + 0.5) / h - k[1, 2]) / k[1, 1]
    xx, yy = np.meshgrid(x, y)
    return np.stack([xx, yy, np.ones_like(xx)], -1)


_FLIP_XY = np.diag([-1.0, -1.0, 1.0, 1.0])


def opencv_c2w_to_mitsuba(c2w: np.ndarray) -> np.ndarray:
    """Mitsuba sensor ``to_world`` for an OpenCV camera-to-world matrix ([..., 4, 4] numpy).

    Examples:
        >>> m = opencv_c2w_to_mitsuba(np.eye(4))
        >>> m.diagonal().tolist()  # Mitsuba's +X is OpenCV's -X (image left), +Y is up
        [-1.0, -1.0, 1.0, 1.0]
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape[-2:] != (4, 4):
        raise ValueError(f"c2w must have shape (..., 4, 4), got {c2w.shape}")
    return c2w @ _FLIP_XY


def mitsuba_to_opencv_c2w(to_world: np.ndarray) -> np.ndarray:
    """The inverse of ``opencv_c2w_to_mitsuba`` (the flip is its own inverse)."""
    return opencv_c2w_to_mitsuba(to_world)
