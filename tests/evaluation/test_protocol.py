"""Evaluation: depth metrics from their definitions, the protocol's per-scene then per-split
means, and the files ``usplat eval`` writes."""

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from usplat_dr.evaluation import depth_metrics, evaluate, synthetic_indices
from usplat_dr.evaluation.metrics import psnr
from usplat_dr.training.checkpoints import load_model


def test_depth_metrics_by_hand():
    # 4 pixels: one uncovered (alpha 0.2), one without ground truth (inf), two counted:
    # predicted depths (alpha-weighted) 1.6 / 0.8 = 2 vs 2.4, and 3 vs 3.
    pred = torch.tensor([[1.6, 3.0], [1.0, 5.0]])
    alpha = torch.tensor([[0.8, 1.0], [0.2, 1.0]])
    gt = torch.tensor([[2.4, 3.0], [1.0, float("inf")]])
    m = depth_metrics(pred, alpha, gt)
    assert m["abs_rel"] == pytest.approx((0.4 / 2.4 + 0) / 2, rel=1e-6)
    assert m["rmse"] == pytest.approx(math.sqrt((0.16 + 0) / 2), rel=1e-6)
    assert m["delta1"] == 1.0  # ratios 1.2 and 1
    m2 = depth_metrics(torch.tensor([1.0, 3.0]), torch.ones(2), torch.tensor([2.0, 3.0]))
    assert m2["delta1"] == pytest.approx(0.5)
    nan = depth_metrics(pred, torch.zeros(2, 2), gt)
    assert math.isnan(nan["abs_rel"])


def test_evaluate_follows_the_protocol_and_writes_files(tmp_path, device, protocol_set):
    # On every available device (CPU always, CUDA where present).
    from usplat_dr.model import UniqueSplat

    root = protocol_set
    indices = synthetic_indices(root)
    assert "standard" in indices
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="baseline")
    dataset = {"name": "synth", "roots": [str(root)], "image_shape": [32, 32]}
    summary = evaluate(model, dataset, {"standard": indices["standard"]}, tmp_path / "eval",
                       progress=False, device=device)
    with open(tmp_path / "eval" / "per_scene.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 == summary["splits"]["standard"]["scenes"]
    # the split's PSNR is the mean over scenes of the per-scene means over targets
    assert summary["splits"]["standard"]["psnr"] == pytest.approx(
        sum(float(r["psnr"]) for r in rows) / 2, rel=1e-6)
    assert summary["splits"]["standard"]["lpips"].startswith("unavailable")
    assert summary["precision"] == "float32" and summary["prune"] == "none"
    assert 0 <= summary["splits"]["standard"]["delta1"] <= 1
    # recompute one scene's PSNR independently from its saved render inputs
    from usplat_dr.data.dataset import dataset_from_section
    from usplat_dr.data.types import model_inputs

    ds = dataset_from_section({**dataset, "evaluation_index": indices["standard"]}, "test")
    example = next(iter(ds))
    from torch.utils.data import default_collate

    batch = default_collate([example])
    with torch.no_grad():  # the exact model: evaluate prunes nothing unless asked
        out = model.eval()(*model_inputs(batch, device), prune=None)
    per_target = psnr(out.color[0].cpu(), batch["target"]["image"][0])
    assert float(rows[0]["psnr"]) == pytest.approx(per_target.mean().item(), rel=1e-5)
    # the material maps reach the example (the shiny and matte PSNRs' masks)
    assert example["target"]["material"].shape == example["target"]["depth"].shape
    assert rows[0]["psnr_matte"] != ""  # indoor rooms: matte walls in every view
    # copying the nearest context view, recomputed in float64 numpy from the example
    ctx, tgt = batch["context"], batch["target"]
    ref = []
    for j in range(tgt["image"].shape[1]):
        dist = [np.linalg.norm(tgt["extrinsics"][0, j, :3, 3].double().numpy()
                               - ctx["extrinsics"][0, i, :3, 3].double().numpy())
                for i in range(ctx["image"].shape[1])]
        diff = (ctx["image"][0, int(np.argmin(dist))].double().numpy()
                - tgt["image"][0, j].double().numpy())
        ref.append(-10 * np.log10(np.mean(diff ** 2)))
    # float32 PSNR per target against float64: 1e-4 relative covers the MSE's rounding
    assert float(rows[0]["psnr_copy"]) == pytest.approx(np.mean(ref), rel=1e-4)
    assert float(rows[0]["psnr_over_copy"]) == pytest.approx(
        float(rows[0]["psnr"]) - float(rows[0]["psnr_copy"]), abs=1e-9)
    assert (tmp_path / "eval" / "renders" / "standard" / f"{example['scene']}.png").is_file()
    saved = json.loads((tmp_path / "eval" / "summary.json").read_text())
    assert saved["parameters"] == sum(p.numel() for p in model.parameters())
    assert saved["prune"] == "none" and saved["image_shape"] == [32, 32]
    std = saved["splits"]["standard"]
    assert std["psnr_over_copy"] == pytest.approx(std["psnr"] - std["psnr_copy"], abs=1e-9)
    assert 0 <= std["scenes_over_copy"] <= std["scenes"]
    with pytest.raises(FileNotFoundError, match="usplat train writes"):
        load_model(tmp_path / "missing.ckpt")


def test_usplat_eval_defaults_to_the_checkpoints_image_shape_and_no_pruning(tmp_path):
    from usplat_dr.cli import main
    from usplat_dr.data.synth import synthesize
    from usplat_dr.model import UniqueSplat

    root = tmp_path / "data"
    synthesize(root, scenes=1, frames=10, resolution=(48, 48), seed=4, spp=4, stage="test",
               previews=0, progress=False, kinds=("indoor",))
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="baseline")
    ckpt = tmp_path / "model.ckpt"  # a usplat checkpoint trained at 32 x 48 (H x W)
    torch.save({"model": model.state_dict(), "model_config": model.cfg.to_dict(), "step": 7,
                "config": {"dataset": {"image_shape": [32, 48]}}}, ckpt)
    common = ["-q", "eval", "--checkpoint", str(ckpt), "--data", str(root), "--splits",
              "standard"]
    assert main([*common, "--out", str(tmp_path / "a")]) == 0
    a = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert a["image_shape"] == [32, 48] and a["prune"] == "none"
    assert a["precision"] == "float32"
    assert main([*common, "--image-shape", "16", "16", "--prune", "--precision", "bfloat16",
                 "--out", str(tmp_path / "b")]) == 0
    b = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert b["image_shape"] == [16, 16] and b["prune"] == "cull+merge1px"
    assert b["precision"] == "bfloat16"


def test_keys_that_cannot_be_scored_are_counted_and_named(tmp_path):
    from usplat_dr.data.synth import synthesize
    from usplat_dr.model import UniqueSplat

    root = tmp_path / "data"
    synthesize(root, scenes=2, frames=10, resolution=(32, 32), seed=6, spp=4, stage="test",
               previews=0, progress=False, kinds=("indoor",))
    index = json.loads(Path(synthetic_indices(root)["standard"]).read_text())
    real = sorted(k for k, v in index.items() if v is not None)
    # one real scene kept, one set to null, one key the data does not have, and one entry
    # naming a frame the scene lacks (the dataset skips it with a warning)
    entry = index[real[0]]
    custom = {real[0]: entry, real[1]: None, "ghost": entry,
              "too_far": {"context": [0, 99], "target": [1]}}
    index_path = tmp_path / "custom.json"
    index_path.write_text(json.dumps(custom))
    model = UniqueSplat.from_preset("tiny", variant="baseline")
    dataset = {"name": "synth", "roots": [str(root)], "image_shape": [32, 32]}
    summary = evaluate(model, dataset, {"custom": str(index_path)}, tmp_path / "eval",
                       progress=False, images_per_split=0)
    split = summary["splits"]["custom"]
    assert split["coverage"] == "scored 1 of 4 keys: 1 null, 2 failed"
    assert split["scenes"] == 1 and sorted(split["failed_scenes"]) == ["ghost", "too_far"]

    (tmp_path / "corrupt.json").write_text('{"a": {"context": [0, 1], "target": [2]')
    with pytest.raises(ValueError, match="corrupt.json is not valid JSON"):
        evaluate(model, dataset, {"c": str(tmp_path / "corrupt.json")}, tmp_path / "e2",
                 progress=False)
    (root / "test" / "index.json").write_bytes(b"\xff\xfe garbage")
    with pytest.raises(ValueError, match="index.json is not valid JSON"):
        evaluate(model, dataset, {"custom": str(index_path)}, tmp_path / "e3", progress=False)


def test_masked_psnr_against_numpy():
    # PSNR over the pixels of the given material codes, per target, against a float64 numpy
    # computation from the definition; a target without such pixels is NaN. 1e-6 dB: float32
    # inputs, float64 means on both sides.
    import numpy as np

    from usplat_dr.evaluation.protocol import SHINY, masked_psnr

    gen = torch.Generator().manual_seed(0)
    pred = torch.rand(2, 3, 6, 7, generator=gen) * 1.2  # some values above 1: clipped
    gt = torch.rand(2, 3, 6, 7, generator=gen)
    material = torch.randint(0, 5, (2, 6, 7), generator=gen).float()
    material[1] = 1.0  # the second target: matte only
    got = masked_psnr(pred, gt, material, SHINY)
    p, g, m = pred.double().clamp(0, 1).numpy(), gt.double().numpy(), material.numpy()
    sel = np.isin(m[0], SHINY)
    mse = ((p[0] - g[0]) ** 2).mean(0)[sel].mean()
    assert got[0] == pytest.approx(-10 * np.log10(mse), abs=1e-6)
    assert math.isnan(got[1])


def test_held_out_scenes_names_the_scored_scenes_in_index_order(protocol_set):
    from usplat_dr.data.view_sampler import read_evaluation_index
    from usplat_dr.evaluation import held_out_scenes, load_example

    dataset, index, scenes = held_out_scenes(protocol_set, size=32)
    entries = read_evaluation_index(index)
    assert scenes == [k for k, v in entries.items() if v is not None] and scenes
    assert held_out_scenes(protocol_set, count=1, size=32)[2] == scenes[:1]
    batch = load_example(dataset, index, scenes[0])
    assert batch["target"]["image"].shape[-2:] == (32, 32)
