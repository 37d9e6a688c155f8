"""The pixelSplat chunk format: reading what plain torch.save wrote, round trips, bad data."""

import json
import logging

import numpy as np
import pytest
import torch

from tests.data.fakes import fake_scene, random_poses, w2c_rows, write_plain_dataset
from usplat_dr.data import (
    BadSceneError,
    ChunkDataset,
    ChunkWriter,
    ViewSamplerAllCfg,
    ViewSamplerEvaluationCfg,
    cameras_to_matrices,
    dataset_cfg,
    decode_image,
    encode_image,
    matrices_to_cameras,
    read_chunk,
)


def test_cameras_decode_matches_numpy_inverse():
    rng = np.random.default_rng(0)
    c2w = random_poses(5, rng)
    rows = np.zeros((5, 18), dtype=np.float32)
    rows[:, :4] = [0.7, 1.2, 0.45, 0.55]
    rows[:, 6:] = w2c_rows(c2w)
    got_c2w, k = cameras_to_matrices(torch.from_numpy(rows))
    # float32 storage of the 3x4 rows: 1e-5 covers its rounding through one 4x4 inverse.
    np.testing.assert_allclose(got_c2w.numpy(), c2w, atol=1e-5)
    np.testing.assert_array_equal(k[0].numpy(), np.array([[0.7, 0, 0.45], [0, 1.2, 0.55],
                                                          [0, 0, 1]], dtype=np.float32))
    back = matrices_to_cameras(got_c2w, k)
    np.testing.assert_allclose(back.numpy(), rows, atol=1e-5)  # same float32 rounding


@pytest.mark.parametrize("bad, match", [("nan", "NaN"), ("singular", "singular"),
                                        ("scaled", "orthonormal"), ("focal", "focal")])
def test_bad_cameras_raise(bad, match):
    rows = torch.zeros(2, 18)
    rows[:, :4] = torch.tensor([0.5, 0.5, 0.5, 0.5])
    rows[:, 6:] = torch.eye(4)[:3].reshape(-1)
    if bad == "nan":
        rows[1, 9] = float("nan")
    elif bad == "singular":
        rows[1, 6:9] = 0.0  # first row of the rotation zero
    elif bad == "scaled":
        rows[1, 6:] *= 2.0
    else:
        rows[0, 0] = 0.0
    with pytest.raises(BadSceneError, match=match):
        cameras_to_matrices(rows)


@pytest.mark.parametrize("fmt", ["png", "jpeg"])
def test_image_encode_decode(fmt):
    rng = np.random.default_rng(1)
    # 8x8 blocks: JPEG's own block size, so the lossy codec stays close.
    img = (rng.random((3, 5, 3)) * 255).astype(np.uint8).repeat(8, 0).repeat(8, 1)
    back = decode_image(encode_image(img, fmt)).permute(1, 2, 0).numpy()
    if fmt == "png":
        np.testing.assert_array_equal(back, img)  # lossless
    else:
        assert back.shape == img.shape
        # Lossy (quality 95, 4:2:0 chroma): a few levels on average, far below the 85 of
        # unrelated random images.
        assert np.abs(back.astype(int) - img).mean() < 8


def test_plain_torch_save_chunk_loads(tmp_path):
    """A chunk written by plain torch.save of the documented structure (RE10K-like, 360x640
    JPEGs) loads into examples with the documented fields and values."""
    scenes = [fake_scene("00a1b2c3d4e5f607", 12, seed=1), fake_scene("1111222233334444", 12,
                                                                     seed=2)]
    write_plain_dataset(tmp_path, "test", [scenes])
    idx = tmp_path / "eval.json"
    idx.write_text(json.dumps({"00a1b2c3d4e5f607": {"context": [1, 9], "target": [3, 4, 8]},
                               "1111222233334444": None}))
    cfg = dataset_cfg("re10k", tmp_path, view_sampler=ViewSamplerEvaluationCfg(str(idx)))
    ds = ChunkDataset(cfg, "test")
    examples = list(ds)
    assert len(examples) == 1 and ds.last_summary["examples"] == 1
    ex = examples[0]
    assert ex["scene"] == "00a1b2c3d4e5f607"
    assert ex["context"]["index"].tolist() == [1, 9]
    assert ex["target"]["index"].tolist() == [3, 4, 8]
    assert ex["context"]["image"].shape == (2, 3, 256, 256)
    assert ex["context"]["image"].dtype == torch.float32
    assert 0 <= ex["context"]["image"].min() and ex["context"]["image"].max() <= 1
    assert ex["target"]["near"].tolist() == [1.0] * 3
    assert ex["target"]["far"].tolist() == [100.0] * 3
    # c2w = inverse of the stored w2c; the crop scales fx by 455/256 (360x640 -> 256x455).
    c2w_ref = np.linalg.inv(np.concatenate([scenes[0]["cameras"][1, 6:].reshape(3, 4).numpy(),
                                            [[0, 0, 0, 1]]]))
    np.testing.assert_allclose(ex["context"]["extrinsics"][0].numpy(), c2w_ref, atol=1e-5)
    assert ex["context"]["intrinsics"][0, 0, 0].item() == pytest.approx(0.5 * 455 / 256)
    assert ex["context"]["intrinsics"][0, 1, 1].item() == pytest.approx(0.5 * 640 / 360)


def test_writer_round_trip(tmp_path):
    scenes = [fake_scene(f"scene{i}", 5, shape=(32, 48), fmt="png", seed=i) for i in range(5)]
    with ChunkWriter(tmp_path, "train", chunk_bytes=1_000) as w:
        for s in scenes:
            w.add(s)
    files = sorted((tmp_path / "train").glob("*.torch"))
    assert len(files) > 1  # the byte budget split the scenes over several chunks
    index = json.loads((tmp_path / "train" / "index.json").read_text())
    back = {s["key"]: s for f in files for s in read_chunk(f)}
    assert set(index) == set(back) == {s["key"] for s in scenes}
    for s in scenes:
        b = back[s["key"]]
        assert index[s["key"]] in [f.name for f in files]
        assert torch.equal(b["cameras"], s["cameras"]) and torch.equal(b["timestamps"],
                                                                       s["timestamps"])
        assert all(torch.equal(x, y) for x, y in zip(b["images"], s["images"]))
    w2 = ChunkWriter(tmp_path, "other")
    w2.add(scenes[0])
    with pytest.raises(ValueError, match="written twice"):
        w2.add(scenes[0])


def test_bad_data_is_skipped_with_warnings_and_counted(tmp_path, caplog):
    good = [fake_scene(f"good{i}", 4, shape=(24, 32), fmt="png", seed=i) for i in range(3)]
    corrupt = fake_scene("corrupt", 4, shape=(24, 32), fmt="png", seed=5)
    corrupt["images"][0] = torch.tensor([1, 2, 3], dtype=torch.uint8)
    nan_cam = fake_scene("nancam", 4, shape=(24, 32), fmt="png", seed=6)
    nan_cam["cameras"][2, 10] = float("nan")
    singular = fake_scene("singular", 4, shape=(24, 32), fmt="png", seed=7)
    singular["cameras"][1, 6:18] = 0.0
    unindexed = fake_scene("unindexed", 4, shape=(24, 32), fmt="png", seed=8)
    stage = write_plain_dataset(tmp_path, "test", [[good[0], corrupt, nan_cam],
                                                   [singular, good[1]], [unindexed, good[2]]])
    index = json.loads((stage / "index.json").read_text())
    del index["unindexed"]
    index["ghost"] = "000099.torch"  # an index entry whose chunk file is missing
    (stage / "index.json").write_text(json.dumps(index))
    (stage / "000003.torch").write_bytes((stage / "000000.torch").read_bytes()[:500])  # truncated

    cfg = dataset_cfg("synth", tmp_path, near=0.5, far=10.0, image_shape=(24, 32),
                      view_sampler=ViewSamplerAllCfg())
    with caplog.at_level(logging.WARNING, logger="usplat_dr.data"):
        ds = ChunkDataset(cfg, "test")
        keys = [ex["scene"] for ex in ds]
    assert keys == ["good0", "good1", "good2"]
    s = ds.last_summary
    assert (s["corrupt image"], s["bad camera"], s["not in index.json"], s["unreadable chunk"],
            s["missing chunk file"]) == (1, 2, 1, 1, 1)
    text = caplog.text
    for name in ("corrupt", "nancam", "singular", "unindexed", "000003.torch", "ghost"):
        assert name in text
    assert text.count("corrupt in") == 1  # one warning per bad scene
    assert "000000.torch" in text  # the warning names the file


def test_missing_root_and_empty_stage_are_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        ChunkDataset(dataset_cfg("re10k", tmp_path / "nope"), "train")
    (tmp_path / "train").mkdir()
    with pytest.raises(FileNotFoundError, match="holds no .torch chunks"):
        ChunkDataset(dataset_cfg("re10k", tmp_path), "train")
    with pytest.raises(ValueError, match="stage"):
        ChunkDataset(dataset_cfg("re10k", tmp_path), "training")
    with pytest.raises(ValueError, match="name must be one of"):
        dataset_cfg("imagenet", tmp_path)


def test_dtu_runs_each_scene_under_numbered_keys(tmp_path):
    # MVSplat's DTU conversion writes one record per scan (key "scan1_train", PNG images of
    # 512 x 640), and its evaluation index names scan1_train_00 .. scan1_train_03: its loader
    # runs each scene test_times_per_scene = 4 times, appending _NN to the key.
    import json

    from tests.data.fakes import fake_scene, write_plain_dataset
    from usplat_dr.data.dataset import dataset_from_section

    scenes = [fake_scene(f"scan{i}_train", 10, shape=(64, 80), fmt="png", seed=i, fx=0.9)
              for i in (1, 4)]
    assert all(bytes(img[:8].tolist()) == b"\x89PNG\r\n\x1a\n" for img in scenes[0]["images"])
    write_plain_dataset(tmp_path, "test", [scenes])
    runs = {f"scan1_train_{t:02d}": {"context": [t, t + 4], "target": [t + 2]}
            for t in range(4)}
    runs.update({f"scan4_train_{t:02d}": None for t in range(4)})
    (tmp_path / "index_dtu.json").write_text(json.dumps(runs))
    section = {"name": "dtu", "roots": [str(tmp_path)], "image_shape": [32, 32],
               "evaluation_index": str(tmp_path / "index_dtu.json")}
    examples = list(dataset_from_section(section, "test"))
    assert [e["scene"] for e in examples] == [f"scan1_train_{t:02d}" for t in range(4)]
    for t, e in enumerate(examples):
        assert e["context"]["index"].tolist() == [t, t + 4]
        assert e["target"]["index"].tolist() == [t + 2]
        assert e["context"]["near"][0] == 2.125 and e["context"]["far"][0] == 4.525
    # without the setting the scans' own keys are looked up, and the index has none of them
    plain = dataset_from_section({**section, "overrides": {"test_times_per_scene": 1}}, "test")
    assert list(plain) == []
    assert plain.last_summary["sampler: no views"] == 2
