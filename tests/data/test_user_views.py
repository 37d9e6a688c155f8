"""A user's images and camera file (COLMAP model or transforms.json) as model inputs: the
cameras of the synthetic truth of tests/data/test_importers.py (the user_scene fixture),
cropped as the datasets crop."""

import numpy as np
import pytest
import torch

from usplat_dr.data.shims import cropped_intrinsics, rescale_and_crop
from usplat_dr.data.user_views import context_views, read_cameras, target_cameras

SHAPE = (32, 32)  # the model's image shape: the 48x64 images are resized to 32x43, cropped


@pytest.mark.parametrize("source", ["colmap", "transforms.json", "nerfstudio folder"])
def test_context_views_hold_the_true_cameras_and_cropped_images(user_scene, source):
    cameras = {"colmap": user_scene.root / "sparse" / "0", "nerfstudio folder": user_scene.root,
               "transforms.json": user_scene.root / "transforms.json"}[source]
    pick = [4, 1]  # not in file order: the images choose their cameras by name
    views = context_views([user_scene.root / "images" / user_scene.names[i] for i in pick],
                          read_cameras(cameras), SHAPE)
    true_k = torch.from_numpy(user_scene.k_norm[pick]).float()
    # users' cameras: the principal point follows the crop (its own test below)
    images, k = rescale_and_crop(torch.from_numpy(user_scene.images[pick]).permute(0, 3, 1, 2),
                                 true_k, SHAPE, move_principal_point=True)
    assert torch.equal(views.images, images)
    # float32 of the float64 user_scene (the importers' own tolerance, 1e-5)
    assert torch.allclose(views.intrinsics, k, atol=1e-5)
    assert torch.allclose(views.extrinsics, torch.from_numpy(user_scene.c2w[pick]).float(),
                          atol=1e-5)
    if source == "colmap":  # sparse points set near/far; they bracket the true depths
        depths = user_scene.depths()
        assert views.near < depths[depths > 0].min() and views.far > depths.max()
    else:
        assert views.near is None and views.far is None


def test_target_cameras_are_cropped_as_images_would_be(user_scene):
    te, tk = target_cameras(read_cameras(user_scene.root / "sparse" / "0"), SHAPE)
    want = cropped_intrinsics(torch.from_numpy(user_scene.k_norm).float(), (48, 64), SHAPE,
                              move_principal_point=True)
    assert torch.allclose(tk, want, atol=1e-5)  # float32 rounding, as above
    assert torch.allclose(te, torch.from_numpy(user_scene.c2w).float(), atol=1e-5)
    # covering 32x32 from 48x64 resizes to 32x43 (43 = round(64 x 32 / 48)) and cuts the
    # width to 32: normalised fx grows by 43/32, fy stays (float32 rounding, 1e-6)
    assert np.isclose(float(tk[0, 0, 0] / user_scene.k_norm[0, 0, 0]), 43 / 32, atol=1e-6)
    assert np.isclose(float(tk[0, 1, 1] / user_scene.k_norm[0, 1, 1]), 1.0, atol=1e-6)


def test_user_mistakes_name_the_argument(user_scene, tmp_path):
    scene = read_cameras(user_scene.root / "sparse" / "0")
    stray = tmp_path / "holiday.png"
    stray.write_bytes((user_scene.root / "images" / user_scene.names[0]).read_bytes())
    with pytest.raises(ValueError, match="image 'holiday.png' has no camera in"):
        context_views([stray, user_scene.root / "images" / user_scene.names[1]], scene, SHAPE)
    with pytest.raises(ValueError, match="needs at least 2 context images"):
        context_views([user_scene.root / "images" / user_scene.names[1]], scene, SHAPE)
    with pytest.raises(FileNotFoundError, match="--images: .*nope.png does not exist"):
        context_views([tmp_path / "nope.png", stray], scene, SHAPE)
    with pytest.raises(FileNotFoundError, match="--cameras .* does not exist"):
        read_cameras(tmp_path / "missing")
    other = tmp_path / "cams.json"  # a .json of another layout
    other.write_text("{}")
    with pytest.raises(ValueError, match="cams.json has no 'frames' list"):
        read_cameras(other)
    with pytest.raises(ValueError, match="--path .*cams.txt: a camera file is a nerfstudio"):
        (tmp_path / "cams.txt").write_text("")
        read_cameras(tmp_path / "cams.txt", what="--path")
    with pytest.raises(FileNotFoundError, match="--path .* does not exist"):
        read_cameras(tmp_path / "missing", what="--path")
    # a camera path under another name than transforms.json, its file_path entries relative
    # to its folder: the same cameras
    renamed = user_scene.root / "camera_path.json"
    renamed.write_text((user_scene.root / "transforms.json").read_text())
    np.testing.assert_array_equal(read_cameras(renamed).extrinsics,
                                  read_cameras(user_scene.root / "transforms.json").extrinsics)
    renamed.unlink()  # (the module's scene is shared)


@pytest.mark.parametrize("shape_in, shape, cx, cy", [((360, 640), (256, 256), 0.42, 0.55),
                                                      ((500, 741), (64, 64), 0.389, 0.5),
                                                      ((756, 1008), (64, 112), 0.5, 0.47)])
def test_the_crop_moves_an_off_centre_principal_point_with_the_pixels(shape_in, shape, cx, cy):
    # float64 reference from the pixel equations: a point's pixel in the original image,
    # scaled by the resize and shifted by the crop's corner, is where the cropped camera must
    # project it (u' = u W_s / W_in - col); the field's shim (cx kept) misses it by
    # (cx - 0.5)(W_s - W) pixels, 13 px for the first case
    from usplat_dr.data.shims import covering_size, cropped_intrinsics

    k = torch.tensor([[[0.9, 0, cx], [0, 1.2, cy], [0, 0, 1]]], dtype=torch.float64)
    h_s, w_s = covering_size(shape_in, shape)
    row, col = (h_s - shape[0]) // 2, (w_s - shape[1]) // 2
    points = np.random.default_rng(0).uniform([-1, -1, 2], [1, 1, 6], (50, 3))
    x, y = points[:, 0] / points[:, 2], points[:, 1] / points[:, 2]
    u = (0.9 * x + cx) * shape_in[1] * w_s / shape_in[1] - col
    v = (1.2 * y + cy) * shape_in[0] * h_s / shape_in[0] - row
    k2 = cropped_intrinsics(k, shape_in, shape, move_principal_point=True)[0].numpy()
    assert np.allclose((k2[0, 0] * x + k2[0, 2]) * shape[1], u, atol=1e-9)
    assert np.allclose((k2[1, 1] * y + k2[1, 2]) * shape[0], v, atol=1e-9)
    kept = cropped_intrinsics(k, shape_in, shape)[0].numpy()
    miss = np.abs((kept[0, 0] * x + kept[0, 2]) * shape[1] - u).max()
    assert (miss > 0.5) == (abs(cx - 0.5) * (w_s - shape[1]) > 0.5)
