"""View samplers (the field's documented behaviour), shims (checked geometrically), and
splitting across workers and ranks."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from tests.data.fakes import fake_scene, write_plain_dataset
from usplat_dr.data import (
    ChunkDataset,
    StepTracker,
    ViewSamplerAllCfg,
    ViewSamplerBoundedCfg,
    ViewSamplerEvaluationCfg,
    ViewSamplingError,
    dataset_cfg,
    get_view_sampler,
    read_evaluation_index,
)
from usplat_dr.data.shims import fov_degrees, normalize_baseline, reflect_views, rescale_and_crop

# ---- bounded sampler ----


@pytest.mark.parametrize("step, gap", [(0, 25), (1, 25), (75_000, 35), (149_999, 44),
                                       (150_000, 45), (300_000, 45)])
def test_bounded_gap_follows_the_schedule(step, gap):
    """min(25 + int(20 * step / 150000), 45), and always exactly that (pixelSplat's max_gap)."""
    s = get_view_sampler(ViewSamplerBoundedCfg(), "train", StepTracker(step))
    g = torch.Generator().manual_seed(0)
    gaps = {int(c[1] - c[0]) for c in (s.sample("x", 300, g)[0] for _ in range(50))}
    assert gaps == {gap}


def test_bounded_left_index_and_targets():
    s = get_view_sampler(ViewSamplerBoundedCfg(), "train", StepTracker(0))
    g = torch.Generator().manual_seed(0)
    lefts, coincide = [], 0
    for _ in range(3000):
        ctx, tgt = s.sample("x", 40, g)
        lefts.append(int(ctx[0]))
        assert len(tgt) == 4 and ((tgt >= ctx[0]) & (tgt <= ctx[1])).all()
        coincide += int(((tgt == ctx[0]) | (tgt == ctx[1])).any())
    # 40 frames, gap 25: left uniform over 0..14 (15 values, 200 draws each on average).
    assert min(lefts) == 0 and max(lefts) == 14
    counts = np.bincount(lefts, minlength=15)
    assert counts.min() > 120  # 5.7 sigma below the mean of 200 for a uniform draw
    # Targets are drawn with replacement from [left, right] inclusive: 4 draws from 26 frames
    # hit a context frame with probability 1 - (24/26)^4 = 27%.
    assert 0.2 < coincide / 3000 < 0.35


def test_targets_beyond_the_context_views_reach_that_far_and_no_further():
    base = ViewSamplerBoundedCfg(warm_up_steps=0, min_distance_between_context_views=6,
                                 max_distance_between_context_views=6)
    beyond = get_view_sampler(replace(base, max_distance_beyond_context_views=4), "train")
    g = torch.Generator().manual_seed(0)
    offsets = []  # a target's distance outside the context pair (0: between them)
    for _ in range(3000):
        ctx, tgt = beyond.sample("x", 24, g)
        assert ((tgt >= 0) & (tgt <= 23)).all()  # clipped to the scene's frames
        offsets += [int(max(ctx[0] - t, t - ctx[1], 0)) for t in tgt]
    assert max(offsets) == 4 and set(range(5)) <= set(offsets)
    # away from the scene's ends, 8 of the 15 frames a target may take lie outside the pair
    assert 0.4 < np.mean(np.array(offsets) > 0) < 0.55
    # 0 beyond is the field's sampler, draw for draw
    plain = get_view_sampler(base, "train")
    zero = get_view_sampler(replace(base, max_distance_beyond_context_views=0), "train")
    g1, g2 = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    for _ in range(50):
        a, b = plain.sample("x", 24, g1), zero.sample("x", 24, g2)
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    # targets beyond the pair and a minimum distance from it contradict each other
    from usplat_dr.training.config import ConfigError, check_sampler_ranges
    both = replace(base, max_distance_beyond_context_views=2, min_distance_to_context_views=1)
    with pytest.raises(ConfigError, match="max_distance_beyond_context_views=2"):
        check_sampler_ranges(both, {})


def test_bounded_full_range_and_test_stage_and_too_few_frames():
    cfg = ViewSamplerBoundedCfg(full_range=True, warm_up_steps=0)
    s = get_view_sampler(cfg, "train")
    g = torch.Generator().manual_seed(0)
    gaps = {int(s.sample("x", 300, g)[0].diff()) for _ in range(2000)}
    assert min(gaps) == 45 and max(gaps) == 192 and len(gaps) > 100
    t = get_view_sampler(ViewSamplerBoundedCfg(), "test")
    ctx, tgt = t.sample("x", 200, g)
    assert ctx.tolist() == [0, 192] and tgt.tolist() == list(range(193))
    with pytest.raises(ViewSamplingError, match="193"):
        t.sample("x", 192, g)
    with pytest.raises(ViewSamplingError):
        get_view_sampler(ViewSamplerBoundedCfg(), "train", StepTracker(0)).sample("x", 25, g)


def test_evaluation_and_all_samplers(tmp_path):
    p = tmp_path / "idx.json"
    p.write_text(json.dumps({"5aca87f95a9412c6": {"context": [58, 133], "target": [84, 102, 129]},
                             "skip": None}))
    s = get_view_sampler(ViewSamplerEvaluationCfg(str(p)), "test")
    ctx, tgt = s.sample("5aca87f95a9412c6", 200)
    assert ctx.tolist() == [58, 133] and tgt.tolist() == [84, 102, 129]
    for key in ("skip", "absent"):
        with pytest.raises(ViewSamplingError):
            s.sample(key, 200)
    with pytest.raises(ViewSamplingError, match="133"):
        s.sample("5aca87f95a9412c6", 100)
    a = get_view_sampler(ViewSamplerAllCfg(), "test")
    assert [x.tolist() for x in a.sample("x", 3)] == [[0, 1, 2], [0, 1, 2]]
    p.write_text(json.dumps({"bad": {"context": [1]}}))
    with pytest.raises(ValueError, match="bad"):
        read_evaluation_index(p)


def test_step_tracker_reaches_dataloader_workers(tmp_path):
    scenes = [fake_scene(f"s{i}", 60, shape=(16, 16), fmt="png", seed=i) for i in range(4)]
    write_plain_dataset(tmp_path, "train", [scenes[:2], scenes[2:]])
    tracker = StepTracker(0)
    cfg = dataset_cfg("synth", tmp_path, near=1.0, far=10.0, image_shape=(16, 16),
                      augment=False, view_sampler=ViewSamplerBoundedCfg())  # RE10K's schedule
    ds = ChunkDataset(cfg, "train", tracker)
    tracker.set_step(150_000)  # after the workers' copies exist: shared memory must carry it
    loader = DataLoader(ds, batch_size=None, num_workers=2, multiprocessing_context="fork")
    gaps = {int(ex["context"]["index"].diff()) for ex in loader}
    assert gaps == {45}


# ---- distribution ----


def _keys(ds: ChunkDataset, workers: int) -> list[str]:
    if workers == 0:
        return [ex["scene"] for ex in ds]
    loader = DataLoader(ds, batch_size=None, num_workers=workers, multiprocessing_context="fork")
    return [ex["scene"] for ex in loader]


def _per_rank(cfg, epoch: int, ranks: int, workers: int) -> list[list[str]]:
    out = []
    for rank in range(ranks):
        ds = ChunkDataset(cfg, "train", rank=rank, world_size=ranks)
        ds.set_epoch(epoch)
        out.append(_keys(ds, workers))
    return out


def test_scenes_split_over_ranks_and_workers_padded_by_wrapping(tmp_path):
    scenes = [fake_scene(f"s{i:02d}", 3, shape=(16, 16), fmt="png", seed=i) for i in range(14)]
    write_plain_dataset(tmp_path, "train", [scenes[i:i + 2] for i in range(0, 14, 2)])
    cfg = dataset_cfg("synth", tmp_path, near=1.0, far=10.0, image_shape=(16, 16),
                      view_sampler=ViewSamplerAllCfg())
    everything = sorted(s["key"] for s in scenes)
    firsts = []
    for epoch in (0, 1):
        per_rank = _per_rank(cfg, epoch, ranks=2, workers=2)
        # 14 scenes over 2 ranks x 2 workers: padded by wrapping to 16, 4 a worker
        assert [len(keys) for keys in per_rank] == [8, 8]
        seen = per_rank[0] + per_rank[1]
        assert sorted(set(seen)) == everything  # every scene...
        assert len(seen) - len(set(seen)) == 2  # ...once, but for the 2 padding repeats
        firsts.append(seen)
    assert firsts[0] != firsts[1]  # reshuffled per epoch
    assert _per_rank(cfg, 0, 2, 2)[0] + _per_rank(cfg, 0, 2, 2)[1] == firsts[0]  # (seed, epoch)
    ds = ChunkDataset(cfg, "train")
    orders = []
    for epoch in (0, 1):
        ds.set_epoch(epoch)
        orders.append(_keys(ds, 0))
    assert sorted(orders[0]) == everything and orders[0] != orders[1]  # reshuffled per epoch
    ds.set_epoch(0)
    assert _keys(ds, 0) == orders[0]  # deterministic for (seed, epoch)


@pytest.mark.parametrize("ranks, workers", [(2, 0), (3, 0), (2, 2)])
def test_one_chunk_feeds_every_rank_and_worker(tmp_path, ranks, workers):
    # the set `usplat synth` writes by default: every scene in one chunk
    scenes = [fake_scene(f"s{i}", 3, shape=(16, 16), fmt="png", seed=i) for i in range(5)]
    write_plain_dataset(tmp_path, "train", [scenes])
    cfg = dataset_cfg("synth", tmp_path, near=1.0, far=10.0, image_shape=(16, 16),
                      view_sampler=ViewSamplerAllCfg())
    per_rank = _per_rank(cfg, 0, ranks, workers)
    total = ranks * max(workers, 1)
    per = -(-5 // total)  # scenes per global worker after padding
    assert [len(keys) for keys in per_rank] == [per * max(workers, 1)] * ranks
    seen = [key for keys in per_rank for key in keys]
    assert sorted(set(seen)) == [s["key"] for s in scenes]
    assert len(seen) == per * total  # the 5 scenes and per * total - 5 padding repeats


def test_evaluation_shards_are_not_padded_and_faults_are_reported_once(tmp_path, caplog):
    scenes = [fake_scene(f"s{i}", 3, shape=(16, 16), fmt="png", seed=i) for i in range(5)]
    stray = fake_scene("stray", 3, shape=(16, 16), fmt="png", seed=9)
    write_plain_dataset(tmp_path, "test", [scenes[:3], scenes[3:]])
    # a scene the index does not know, in the first chunk, read by both workers of rank 0
    torch.save(scenes[:3] + [stray], tmp_path / "test" / "000000.torch")
    cfg = dataset_cfg("synth", tmp_path, near=1.0, far=10.0, image_shape=(16, 16),
                      view_sampler=ViewSamplerAllCfg())
    summaries = []
    seen = []
    for rank in range(3):
        ds = ChunkDataset(cfg, "test", rank=rank, world_size=3)
        seen += [ex["scene"] for ex in ds]
        summaries.append(ds.last_summary)
    assert sorted(seen) == [s["key"] for s in scenes]  # no padding in evaluation
    assert sum(s["not in index.json"] for s in summaries) == 1  # reported once, not twice

# ---- shims ----


def _project(c2w: np.ndarray, k: np.ndarray, p: np.ndarray, hw) -> np.ndarray:
    """Pixel coordinates (x right, y down) of world point p: independent pinhole model."""
    q = np.linalg.inv(c2w) @ np.append(p, 1.0)
    return np.array([(k[0, 0] * q[0] / q[2] + k[0, 2]) * hw[1], (k[1, 1] * q[1] / q[2] + k[1, 2])
                     * hw[0]])


def test_crop_keeps_projection_consistent():
    """After resize-to-cover + centre crop, the new intrinsics project a point where the image
    content moved: (u * s - col, v * s - row)."""
    rng = np.random.default_rng(0)
    img = np.zeros((360, 640, 3), dtype=np.uint8)
    img[200:216, 400:416] = 255  # a marker around pixel (x 408, y 208)
    k = np.array([[0.9, 0, 0.5], [0, 1.6, 0.5], [0, 0, 1]])
    images, k2 = rescale_and_crop(torch.from_numpy(img).permute(2, 0, 1)[None],
                                  torch.tensor(k, dtype=torch.float32)[None], (256, 256))
    s = 256 / 360  # cover: 360x640 -> 256x455, crop columns 99..354
    col = (455 - 256) // 2
    c2w = np.eye(4)
    for _ in range(5):
        p = np.append(rng.uniform(-0.3, 0.3, 2), rng.uniform(2, 5))
        u0 = _project(c2w, k, p, (360, 640))
        u1 = _project(c2w, k2[0].double().numpy(), p, (256, 256))
        # The field keeps cx = 0.5, i.e. it assumes a symmetric crop of 99.5 columns, while
        # the pixels move by 99 (455 - 256 is odd): a half-pixel shift we reproduce on
        # purpose (checkpoints were trained with it). Rounding 640 * 256 / 360 to 455
        # changes the scale by 0.02%: at most 0.05 px here.
        np.testing.assert_allclose(u1, [u0[0] * 455 / 640 - (455 - 256) / 2, u0[1] * s],
                                   atol=0.06)
    marker = images[0, 0].float().numpy()
    ys, xs = np.nonzero(marker > 128)
    np.testing.assert_allclose([xs.mean() + 0.5, ys.mean() + 0.5],
                               [408 * 455 / 640 - col, 208 * s], atol=0.6)  # Lanczos ringing


def test_reflect_mirrors_world_and_images():
    rng = np.random.default_rng(1)
    c2w = np.eye(4)
    c2w[:3, 3] = [0.3, -0.1, -1.0]
    k = np.array([[0.7, 0, 0.42], [0, 0.8, 0.5], [0, 0, 1]])
    views = {"extrinsics": torch.tensor(c2w, dtype=torch.float32)[None],
             "intrinsics": torch.tensor(k, dtype=torch.float32)[None],
             "image": torch.arange(3 * 4 * 5).reshape(1, 3, 4, 5)}
    flipped = reflect_views(views)
    assert torch.equal(flipped["image"], views["image"].flip(-1))
    for _ in range(5):
        p = rng.uniform(-0.5, 0.5, 3) + [0, 0, 3]
        u = _project(c2w, k, p, (4, 5))
        u_m = _project(flipped["extrinsics"][0].double().numpy(),
                       flipped["intrinsics"][0].double().numpy(), p * [-1, 1, 1], (4, 5))
        np.testing.assert_allclose(u_m, [5 - u[0], u[1]], atol=1e-5)  # float32 matrices


def test_fov_and_baseline():
    fx = 0.6
    k = torch.tensor([[fx, 0, 0.5], [0, fx * 1.5, 0.5], [0, 0, 1]])
    fov = fov_degrees(k)
    assert fov[0].item() == pytest.approx(math.degrees(2 * math.atan(0.5 / fx)), abs=1e-4)
    assert fov[1].item() == pytest.approx(math.degrees(2 * math.atan(0.5 / (1.5 * fx))), abs=1e-4)
    e = torch.eye(4).repeat(2, 1, 1)
    e[1, :3, 3] = torch.tensor([0.0, 0.0, 4.0])
    views = {"extrinsics": e, "near": torch.ones(2), "far": torch.full((2,), 100.0)}
    ex, scale = normalize_baseline({"context": views, "target": views}, scale_bounds=True)
    assert scale == 4.0 and ex["target"]["extrinsics"][1, 2, 3].item() == 1.0
    assert ex["context"]["far"].tolist() == [25.0, 25.0]
    e[1] = torch.eye(4)
    with pytest.raises(ValueError, match="1e-3"):
        normalize_baseline({"context": views, "target": views}, scale_bounds=False)


def test_wide_fov_views_are_skipped(tmp_path):
    wide = fake_scene("wide", 4, shape=(16, 16), fmt="png", fx=0.2)  # 136 degrees
    ok = fake_scene("ok", 4, shape=(16, 16), fmt="png", fx=0.5)  # 90 degrees
    write_plain_dataset(tmp_path, "test", [[wide, ok]])
    cfg = dataset_cfg("synth", tmp_path, near=1.0, far=10.0, image_shape=(16, 16),
                      view_sampler=ViewSamplerAllCfg())
    ds = ChunkDataset(cfg, "test")
    assert [e["scene"] for e in ds] == ["ok"] and ds.last_summary["fov over max_fov"] == 1
