"""``usplat render --images A B --cameras FILE``: a user's own images and camera file (COLMAP
or transforms.json, from the synthetic truth of tests/data/test_importers.py) give novel views,
PNG frames, a video and a PLY with the shipped checkpoint, and the frames are what
``usplat_dr.load(...).predict(...)`` renders."""

import numpy as np
import pytest
from PIL import Image
from plyfile import PlyData

import usplat_dr
from usplat_dr.cli import main
from usplat_dr.data.user_views import context_views, read_cameras
from usplat_dr.io.images import to_uint8
from usplat_dr.jobs.render import targets


def test_two_images_and_a_colmap_model_give_frames_a_video_and_a_ply(user_scene, tmp_path, capsys):
    # no --checkpoint: own photographs get the largest shipped (c), full-128 (the frames are
    # compared with its renders below)
    images = [str(user_scene.root / "images" / user_scene.names[i]) for i in (1, 3)]
    sparse = str(user_scene.root / "sparse" / "0")
    out = tmp_path / "out"
    assert main(["-q", "render", "--images", *images,
                 "--cameras", sparse, "--frames", "4", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "gaussians_frame0000.ply" in printed and "4 frames" in printed
    assert "near/far " in printed and "(from the sparse points; --near/--far to set it)" in printed
    # the square crop of 48x64 photos drops a quarter: said, with the shape that keeps them
    # (covering 128x128 resizes to 128x171: 128/171 = 75% kept; 128 x 48/64 = 96 rows)
    assert ("the 128x128 crop keeps 75% of each 48x64 photo (drops 13% at the left and at the "
            "right): --image-shape 96 128 keeps its aspect") in printed
    frames = sorted((out / "frames").glob("*.png"))
    assert len(frames) == 4
    assert len(list(out.glob("video.*"))) == 1
    # pixel-aligned: one Gaussian per context pixel (2 views x 128 x 128, the model's size)
    assert len(PlyData.read(str(out / "gaussians_frame0000.ply"))["vertex"]) == 2 * 128 * 128

    # the frames' colour half is what the Python API renders, to the uint8 of the PNG: at most
    # one level apart in at most 0.1% of the values. At 128x128 the two calls' float32 colours
    # differ in their last bits, so a value on a rounding boundary may land on the neighbouring
    # level (3 of 196,608 values, 2026-11-29; at 64x64 they matched exactly; the cause, likely
    # a different summation order in one of the two calls, is not pinned down). Another model
    # or camera differs by tens of levels in most values.
    model = usplat_dr.load("full-128")
    views = context_views(images, read_cameras(sparse), (128, 128))
    te, tk = targets("orbit", views.extrinsics, views.intrinsics, 4, (128, 128))
    pred = model.predict(views.images, intrinsics=views.intrinsics, extrinsics=views.extrinsics,
                         target_intrinsics=tk, target_extrinsics=te, near=views.near,
                         far=views.far)
    for i, png in enumerate(frames):
        colour = np.asarray(Image.open(png))[:, :128].astype(int)
        diff = np.abs(colour - to_uint8(pred.color[i].permute(1, 2, 0).numpy()).astype(int))
        assert diff.max() <= 1 and (diff > 0).mean() <= 1e-3, (diff.max(), (diff > 0).sum())


def test_a_transforms_json_with_its_cameras_as_the_path(user_scene, tmp_path):
    images = [str(user_scene.root / "images" / user_scene.names[i]) for i in (0, 2)]
    cameras = str(user_scene.root / "transforms.json")
    out = tmp_path / "out"
    assert main(["-q", "render", "--checkpoint", "baseline-64", "--images", *images,
                 "--cameras", cameras, "--near", "2", "--far", "7", "--path", cameras,
                 "--out", str(out)]) == 0
    assert len(list((out / "frames").glob("*.png"))) == len(user_scene.names)  # every camera


def test_a_range_far_outside_the_training_range_is_warned_about(user_scene, tmp_path, caplog):
    images = [str(user_scene.root / "images" / user_scene.names[i]) for i in (0, 2)]
    cameras = str(user_scene.root / "transforms.json")

    def render(near: str, far: str) -> list[str]:
        caplog.clear()
        assert main(["-q", "render", "--checkpoint", "baseline-64", "--images", *images,
                     "--cameras", cameras, "--near", near, "--far", far, "--frames", "2",
                     "--out", str(tmp_path / "out")]) == 0
        return [r.getMessage() for r in caplog.records if "training range" in r.getMessage()]

    assert render("2", "7") == []  # the scene's own range, inside the shipped models' range
    # the same scene in millimetres: the shipped models trained on near 0.2-2.1, far 4.5-100
    (warning,) = render("2000", "7000")
    assert "near/far 2000 / 7000" in warning and "near 0.2-2.125, far 4.525-100" in warning


def test_a_path_is_predicted_a_few_targets_at_a_time_and_bounded(user_scene, tmp_path,
                                                                  monkeypatch, capsys):
    from usplat_dr.jobs import render as render_job

    images = [str(user_scene.root / "images" / user_scene.names[i]) for i in (0, 2)]
    cameras = str(user_scene.root / "transforms.json")
    args = ["-q", "render", "--checkpoint", "full-64", "--images", *images, "--cameras",
            cameras, "--near", "2", "--far", "7", "--path", cameras]
    frames = {}
    for chunk in (2, 8):  # 6 cameras: three chunks of 2, or one
        monkeypatch.setattr(render_job, "PATH_CHUNK", chunk)
        assert main([*args, "--out", str(tmp_path / f"c{chunk}")]) == 0
        frames[chunk] = [np.asarray(Image.open(f)) for f in
                         sorted((tmp_path / f"c{chunk}" / "frames").glob("*.png"))]
    assert len(frames[2]) == len(user_scene.names)
    # each target is predicted on its own (its own Delta W in (c)): chunks change nothing but
    # the float rounding of convolutions batched over 2 or 6 targets (oneDNN may pick other
    # kernels for other batch sizes, and by what the process ran before: after an in-process
    # PLY export, 2026-12-04), which flips single 8-bit levels, most in the depth half, whose
    # colour map steepens them: measured 1 pixel of 12,288 by 1 level in one run, by 2 levels
    # in another; allowed: 3 levels, on at most 1% of the pixels of a frame (mixing targets
    # up would move whole regions by tens of levels)
    for a, b in zip(frames[2], frames[8]):
        diff = np.abs(a.astype(int) - b)
        assert diff.max() <= 3 and (diff > 0).mean() <= 0.01
    monkeypatch.setattr(render_job, "MAX_PATH_CAMERAS", 5)
    capsys.readouterr()
    assert main([*args, "--out", str(tmp_path / "long")]) == 2
    assert "holds 6 cameras (at most 5 frames)" in capsys.readouterr().err


@pytest.mark.parametrize("extra, needle", [
    ([], "give --data (a dataset in the chunk format) or --images A B --cameras FILE"),
    # without --cameras the photos are posed by COLMAP first: random noise images share no
    # feature, so none registers, and the message says which and why
    (["--images", "{a}", "{b}"], "COLMAP registered 0 of 2 photos"),
    # a transforms.json holds no sparse points: near/far come from a plane sweep, which finds
    # no match between two unrelated noise images and asks for them
    (["--images", "{a}", "{b}", "--cameras", "{json}"],
     "match at 0 of 18432 pixels (textureless, or not overlapping): give --near and --far"),
    (["--images", "{a}", "{b}", "--cameras", "{json}", "--near", "1"],
     "give both --near and --far"),
])
def test_mistakes_name_the_argument(user_scene, capsys, monkeypatch, tmp_path, extra, needle):
    monkeypatch.chdir(tmp_path)  # the default --out (outputs/render, its pose/ folder) is here
    fill = {"{a}": str(user_scene.root / "images" / user_scene.names[0]),
            "{b}": str(user_scene.root / "images" / user_scene.names[1]),
            "{json}": str(user_scene.root / "transforms.json")}
    assert main(["-q", "render", "--checkpoint", "full-64",
                 *[fill.get(x, x) for x in extra]]) == 2
    assert needle in capsys.readouterr().err


def test_the_readme_python_block_runs_on_a_users_project(user_scene):
    """The README's ``predict`` block, with its ``project/`` paths pointed at a generated
    COLMAP project, runs as written and renders what ``usplat render --path`` would."""
    from tests.test_readme import README, fenced_blocks

    [block] = [b for b in fenced_blocks(README.read_text(), "python") if ".predict(" in b]
    root = user_scene.root
    code = (block.replace("project/sparse/0", str(root / "sparse" / "0"))
            .replace("project/images/a.png", str(root / "images" / user_scene.names[1]))
            .replace("project/images/b.png", str(root / "images" / user_scene.names[3])))
    assert code != block and "project/" not in code
    scope: dict = {}
    exec(compile(code, "README.md", "exec"), scope)  # noqa: S102  (the README's own code)
    pred = scope["pred"]
    assert pred.color.shape == (len(user_scene.names), 3, 64, 64)
    assert len(pred.gaussians) == len(user_scene.names)


def test_a_shorter_render_into_the_same_folder_leaves_no_stale_frames(tmp_path):
    from usplat_dr.jobs.render import write_frames

    folder = tmp_path / "out" / "frames"
    write_frames(np.zeros((5, 4, 8, 3)), folder)
    (tmp_path / "out" / ".frames.partial").mkdir()  # a killed render's leftovers
    (tmp_path / "out" / ".frames.partial" / "0007.png").write_bytes(b"stale")
    write_frames(np.full((2, 4, 8, 3), 1.0), folder)
    assert sorted(p.name for p in folder.iterdir()) == ["0000.png", "0001.png"]
    assert np.asarray(Image.open(folder / "0001.png")).min() == 255
    assert not (tmp_path / "out" / ".frames.partial").exists()
