import numpy as np
from PIL import Image

from usplat_dr.io.images import colorize_depth, grid, save_png, to_uint8


def test_to_uint8_rounds_and_clips():
    assert to_uint8(np.array([-1.0, 0.0, 0.5, 1.0, 2.0, np.nan])).tolist() == [0, 0, 128, 255,
                                                                                255, 0]


def test_save_png_round_trip_and_leaves_no_temp_files(tmp_path):
    img = np.random.default_rng(0).random((5, 7, 3))
    path = save_png(tmp_path / "a" / "x.png", img)
    back = np.asarray(Image.open(path))
    assert np.array_equal(back, to_uint8(img))
    assert [p.name for p in path.parent.iterdir()] == ["x.png"]


def test_colorize_depth_orders_near_bright_and_masks_background():
    depth = np.array([[1.0, 2.0, 4.0, 0.0]])
    alpha = np.array([[1.0, 1.0, 1.0, 0.0]])
    rgb = colorize_depth(depth, alpha, near=1.0, far=4.0)
    luminance = rgb.sum(-1)[0]
    assert luminance[0] > luminance[1] > luminance[2] > 0
    assert luminance[3] == 0


def test_grid_shape():
    tiles = [[np.zeros((4, 6, 3))] * 3, [np.ones((4, 6, 3))] * 2]
    assert grid(tiles, pad=2).shape == (2 * 6 + 2, 3 * 8 + 2, 3)
