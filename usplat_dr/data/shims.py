"""Shims applied to examples as the field applies them (pixelSplat ``src/dataset/shims``).

An example is pixelSplat's dict: ``{"context": views, "target": views, "scene": key}`` where
``views`` holds ``extrinsics`` [V, 4, 4] (OpenCV c2w), ``intrinsics`` [V, 3, 3] (normalised),
``image`` [V, 3, H, W] (float in [0, 1]), ``near`` [V], ``far`` [V], ``index`` [V] (int64 frame
indices) and, for synthetic data, ``depth`` [V, H, W] (camera-space z, +inf on a miss) and
``material`` [V, H, W] (``usplat synth``'s material codes as floats; resized like depth).
"""

import math

import numpy as np
import torch
from jaxtyping import Float
from PIL import Image
from torch import Tensor

from usplat_dr.data.chunks import MAX_IMAGE_PIXELS


def fov_degrees(intrinsics: Float[Tensor, "*batch 3 3"]) -> Float[Tensor, "*batch 2"]:
    """Horizontal and vertical field of view in degrees, measured as the field does: the
    angle between the rays through the midpoints of opposite image edges.

    Examples:
        >>> k = torch.tensor([[0.5, 0, 0.5], [0, 0.5, 0.5], [0, 0, 1]])
        >>> fov_degrees(k).round().tolist()
        [90.0, 90.0]
    """
    k_inv = torch.linalg.inv(intrinsics.double())

    def ray(x: float, y: float) -> Tensor:
        r = k_inv @ torch.tensor([x, y, 1.0], dtype=torch.float64)
        return torch.nn.functional.normalize(r, dim=-1)

    def angle(a: Tensor, b: Tensor) -> Tensor:
        return (a * b).sum(-1).clamp(-1, 1).acos()

    fov_x = angle(ray(0.0, 0.5), ray(1.0, 0.5))
    fov_y = angle(ray(0.5, 0.0), ray(0.5, 1.0))
    fov = torch.stack([fov_x, fov_y], -1)
    return torch.rad2deg(fov).float()


def _resize(image: Tensor, shape: tuple[int, int]) -> Tensor:
    h, w = shape
    if image.dtype == torch.uint8:  # [3, H, W]
        im = Image.fromarray(image.permute(1, 2, 0).numpy())
        out = np.asarray(im.resize((w, h), Image.LANCZOS)).copy()
        return torch.from_numpy(out).permute(2, 0, 1)
    # Float maps (depth): nearest neighbour keeps depths real (no mixing across edges).
    im = Image.fromarray(image.float().numpy(), mode="F")
    out = im.resize((w, h), Image.NEAREST)
    return torch.from_numpy(np.asarray(out).copy()).to(image.dtype)


def rescale_and_crop(
    images: Tensor,  # uint8 [V, 3, H, W] (Lanczos) or float [V, H, W] depth (nearest)
    intrinsics: Float[Tensor, "view 3 3"],
    shape: tuple[int, int],
    move_principal_point: bool = False,
) -> tuple[Tensor, Float[Tensor, "view 3 3"]]:
    """Resize so the image covers ``shape``, then centre-crop to it; fx, fy scale by the crop
    (cx, cy stay as stored, as in the field's datasets, whose principal points are centred;
    ``move_principal_point``: moved by the crop, right for any principal point, as users'
    own images need: ``cropped_intrinsics``). Images are resized as uint8 with PIL Lanczos.

    Examples:
        >>> imgs = torch.zeros(1, 3, 360, 640, dtype=torch.uint8)
        >>> k = torch.tensor([[[0.9, 0, 0.5], [0, 1.6, 0.5], [0, 0, 1]]])
        >>> out, k2 = rescale_and_crop(imgs, k, (256, 256))
        >>> tuple(out.shape), round(k2[0, 0, 0].item(), 4), round(k2[0, 1, 1].item(), 4)
        ((1, 3, 256, 256), 1.5996, 1.6)
    """
    h_in, w_in = images.shape[-2:]
    h_out, w_out = shape
    h_scaled, w_scaled = covering_size(images.shape[-2:], shape)
    # the cap decoding applies: a 1 x 4,000,000 frame passes it, but covering a 32x32 crop
    # would make it 32 x 128,000,000 (the scene is skipped)
    if h_scaled * w_scaled > MAX_IMAGE_PIXELS:
        raise ValueError(f"a {h_in}x{w_in} image would be resized to {h_scaled}x{w_scaled} "
                         f"to cover {h_out}x{w_out}: more than {MAX_IMAGE_PIXELS:,} pixels")
    if (h_scaled, w_scaled) != (h_in, w_in):
        images = torch.stack([_resize(im, (h_scaled, w_scaled)) for im in images])
    row, col = (h_scaled - h_out) // 2, (w_scaled - w_out) // 2
    images = images[..., row:row + h_out, col:col + w_out]
    return images, cropped_intrinsics(intrinsics, (h_in, w_in), shape, move_principal_point)


def covering_size(shape_in, shape: tuple[int, int]) -> tuple[int, int]:
    """The size an image of ``shape_in`` is resized to so that it covers ``shape``."""
    (h_in, w_in), (h_out, w_out) = shape_in, shape
    scale = max(h_out / h_in, w_out / w_in)
    return round(h_in * scale), round(w_in * scale)


def cropped_intrinsics(intrinsics: Float[Tensor, "view 3 3"], shape_in: tuple[int, int],
                       shape: tuple[int, int], move_principal_point: bool = False
                       ) -> Float[Tensor, "view 3 3"]:
    """The normalised intrinsics of an image of ``shape_in`` after ``rescale_and_crop`` to
    ``shape``, without the image (a target camera). With ``move_principal_point`` the
    principal point follows the crop: cx' = (cx W_s - col) / W (W_s the resized width, col
    the crop's first column), likewise cy; without, it stays as stored (the field's shim,
    exact only for a centred one).

    Examples:
        >>> k = torch.tensor([[[0.9, 0, 0.5], [0, 1.6, 0.5], [0, 0, 1]]])
        >>> round(cropped_intrinsics(k, (360, 640), (256, 256))[0, 0, 0].item(), 4)
        1.5996
        >>> k[0, 0, 2] = 0.42  # off-centre: 0.42 x 455 - 99 = 92.1 of 256 pixels
        >>> round(cropped_intrinsics(k, (360, 640), (256, 256), True)[0, 0, 2].item(), 4)
        0.3598
    """
    h_scaled, w_scaled = covering_size(shape_in, shape)
    intrinsics = intrinsics.clone()
    intrinsics[:, 0, 0] *= w_scaled / shape[1]
    intrinsics[:, 1, 1] *= h_scaled / shape[0]
    if move_principal_point:
        row, col = (h_scaled - shape[0]) // 2, (w_scaled - shape[1]) // 2
        intrinsics[:, 0, 2] = (intrinsics[:, 0, 2] * w_scaled - col) / shape[1]
        intrinsics[:, 1, 2] = (intrinsics[:, 1, 2] * h_scaled - row) / shape[0]
    return intrinsics


def crop_views(views: dict, shape: tuple[int, int]) -> dict:
    """``rescale_and_crop`` applied to one side of an example (image and, if present, depth
    and material maps)."""
    views = dict(views)
    image, intrinsics = rescale_and_crop(views["image"], views["intrinsics"], shape)
    for key in ("depth", "material"):
        if key in views:
            views[key], _ = rescale_and_crop(views[key], views["intrinsics"], shape)
    views["image"], views["intrinsics"] = image, intrinsics
    return views


def reflect_views(views: dict) -> dict:
    """Mirror the views left-right: images flipped along width, extrinsics conjugated by
    diag(-1, 1, 1, 1) (a mirrored world seen by mirrored cameras), and cx -> 1 - cx (the
    field leaves cx, which is the same for its cx = 0.5)."""
    views = dict(views)
    reflect = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))
    views["extrinsics"] = reflect @ views["extrinsics"] @ reflect
    views["image"] = views["image"].flip(-1)
    for key in ("depth", "material"):
        if key in views:
            views[key] = views[key].flip(-1)
    k = views["intrinsics"].clone()
    k[:, 0, 2] = 1.0 - k[:, 0, 2]
    views["intrinsics"] = k
    return views


def augment_flip(example: dict, generator: torch.Generator, p: float = 0.5) -> dict:
    """Training augmentation of the field: with probability ``p`` mirror context and targets
    together."""
    if torch.rand((), generator=generator).item() >= p:
        return example
    return {**example, "context": reflect_views(example["context"]),
            "target": reflect_views(example["target"])}


def normalize_baseline(example: dict, scale_bounds: bool) -> tuple[dict, float]:
    """Divide all translations by the distance between the first two context cameras
    (``make_baseline_1``); with ``scale_bounds`` divide near/far too. Raises ``ValueError``
    when that distance is below 1e-3 (the field skips such examples)."""
    ctx = example["context"]["extrinsics"]
    scale = (ctx[0, :3, 3] - ctx[-1, :3, 3]).norm().item()
    if not math.isfinite(scale) or scale < 1e-3:
        raise ValueError(f"context baseline {scale:.2g} is below 1e-3")
    out = dict(example)
    for side in ("context", "target"):
        views = dict(example[side])
        e = views["extrinsics"].clone()
        e[:, :3, 3] /= scale
        views["extrinsics"] = e
        if scale_bounds:
            views["near"] = views["near"] / scale
            views["far"] = views["far"] / scale
        if "depth" in views:
            views["depth"] = views["depth"] / scale
        out[side] = views
    return out, scale
