"""A user's own images and camera file as model inputs, without a dataset (``usplat render
--images A B --cameras FILE``, ``UniqueSplat.predict``).

The camera file is what users have: a COLMAP sparse model (its folder) or a nerfstudio
``transforms.json`` (the file, or the folder holding it), read by ``usplat_dr.data.importers``
with its conventions. Images are matched to cameras by file name, then resized to cover the
model's image shape and centre-cropped, the intrinsics following (``rescale_and_crop``, as the
datasets do, and the principal point moved by the crop: a user's camera may have an
off-centre one, where the field's shim, which keeps it, would shift every ray).
"""

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from usplat_dr.data.importers import (
    ImportedScene,
    load_image,
    near_far_from_points,
    read_colmap,
    read_nerfstudio,
)
from usplat_dr.data.shims import covering_size, cropped_intrinsics, rescale_and_crop


@dataclass
class UserViews:
    """Context views ready for the model: ``images`` uint8 [V, 3, H, W], ``extrinsics``
    [V, 4, 4] camera-to-world (OpenCV), ``intrinsics`` [V, 3, 3] normalised for the cropped
    images; ``near``/``far`` from the sparse points, or None when the file has none."""

    images: torch.Tensor
    extrinsics: torch.Tensor
    intrinsics: torch.Tensor
    near: float | None
    far: float | None


def read_cameras(path: str | os.PathLike, ignore_distortion: bool = False,
                 what: str = "--cameras") -> ImportedScene:
    """The cameras of a COLMAP model folder (``sparse/0``, or a project folder holding one) or
    of a nerfstudio-style JSON file (``transforms.json``, or any ``.json`` in that layout, such
    as a camera path; or the folder holding a ``transforms.json``). ``what`` names the
    argument in errors."""
    path = Path(path)
    if path.is_file() and path.suffix == ".json":
        return read_nerfstudio(path.parent, ignore_distortion, name=path.name,
                               distinct_images=what != "--path")
    if path.is_file():
        raise ValueError(f"{what} {path}: a camera file is a nerfstudio-style .json "
                         "(transforms.json) or a COLMAP model folder")
    if path.is_dir() and (path / "transforms.json").is_file():
        return read_nerfstudio(path, ignore_distortion, distinct_images=what != "--path")
    if path.is_dir():
        return read_colmap(path, ignore_distortion=ignore_distortion)
    raise FileNotFoundError(f"{what} {path} does not exist: pass a COLMAP model folder "
                            "(sparse/0) or a nerfstudio transforms.json")


def _match(images: list[Path], scene: ImportedScene) -> list[int]:
    """The camera index of each image, by file name."""
    names = {p.name: i for i, p in enumerate(scene.image_paths)}
    out = []
    for image in images:
        if image.name not in names:
            some = ", ".join(sorted(names)[:5]) + (", ..." if len(names) > 5 else "")
            raise ValueError(f"image {image.name!r} has no camera in {scene.source} (its "
                             f"images: {some}): name the images as the camera file does")
        out.append(names[image.name])
    return out


def context_views(images: list[str | os.PathLike], scene: ImportedScene,
                  image_shape: tuple[int, int]) -> UserViews:
    """The ``images`` (files named as in ``scene``'s camera file, at least 2) cropped to
    ``image_shape`` (H, W), with their cameras."""
    paths = [Path(p) for p in images]
    if len(paths) < 2:
        raise ValueError(f"--images needs at least 2 context images, got {len(paths)}")
    for p in paths:
        if not p.is_file():
            raise FileNotFoundError(f"--images: {p} does not exist")
    idx = _match(paths, scene)
    loaded = [torch.from_numpy(np.array(load_image(
        p, tuple(int(n) for n in scene.image_shapes[i]), None))).permute(2, 0, 1)
              for p, i in zip(paths, idx)]
    intrinsics = torch.from_numpy(scene.intrinsics[idx]).float()
    cropped, ks = [], []
    for im, k in zip(loaded, intrinsics):  # one at a time: the images may differ in size
        c, k2 = rescale_and_crop(im[None], k[None], image_shape, move_principal_point=True)
        cropped.append(c[0])
        ks.append(k2[0])
    near = far = None
    if scene.points is not None and len(scene.points):
        near, far = near_far_from_points(scene.points, scene.extrinsics, scene.intrinsics)
    return UserViews(images=torch.stack(cropped),
                     extrinsics=torch.from_numpy(scene.extrinsics[idx]).float(),
                     intrinsics=torch.stack(ks), near=near, far=far)


def target_cameras(scene: ImportedScene, image_shape: tuple[int, int]
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Every camera of ``scene`` as a target rendered at ``image_shape``: extrinsics
    [N, 4, 4] and intrinsics [N, 3, 3] (cropped as the images would be)."""
    ks = [cropped_intrinsics(torch.from_numpy(k).float()[None], tuple(int(n) for n in s),
                             image_shape, move_principal_point=True)[0]
          for k, s in zip(scene.intrinsics, scene.image_shapes)]
    return torch.from_numpy(np.asarray(scene.extrinsics)).float(), torch.stack(ks)


#: The crop dropping less than this share of a photo goes unmentioned (``crop_advice``).
CROP_QUIET = 0.1


def crop_advice(shape_in: tuple[int, int], shape: tuple[int, int], multiple: int = 16
                ) -> str | None:
    """What the crop of a ``shape_in`` (H, W) photo to ``shape`` drops, and an image shape
    with the photo's aspect (the long side kept, the short one a multiple of ``multiple``);
    None when it drops under ``CROP_QUIET`` of the photo.

    Examples:
        >>> print(crop_advice((1008, 756), (64, 64)))  # doctest: +NORMALIZE_WHITESPACE
        the 64x64 crop keeps 75% of each 1008x756 photo (drops 12% at the top and at the
        bottom): --image-shape 64 48 keeps its aspect
        >>> crop_advice((480, 640), (48, 64)) is None
        True
    """
    h_s, w_s = covering_size(shape_in, shape)
    kept = shape[0] * shape[1] / (h_s * w_s)
    if kept > 1 - CROP_QUIET:
        return None
    (h, w), long_side = shape_in, max(shape)
    if h >= w:
        suggest = (long_side, max(multiple, round(long_side * w / h / multiple) * multiple))
        where = "at the top and at the bottom"
    else:
        suggest = (max(multiple, round(long_side * h / w / multiple) * multiple), long_side)
        where = "at the left and at the right"
    return (f"the {shape[0]}x{shape[1]} crop keeps {kept:.0%} of each {h}x{w} photo (drops "
            f"{(1 - kept) / 2:.0%} {where}): --image-shape {suggest[0]} {suggest[1]} keeps its "
            "aspect")
