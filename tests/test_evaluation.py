"""Evaluation: depth metrics from their definitions, the protocol's per-scene then per-split
means, the files ``usplat eval`` writes, and ``usplat demo --quick`` end to end."""

import csv
import json
import math

import pytest
import torch

from usplat_dr.evaluation import depth_metrics, evaluate, load_model, synthetic_indices
from usplat_dr.metrics import psnr


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


def test_evaluate_follows_the_protocol_and_writes_files(tmp_path):
    from usplat_dr.data.synth import synthesize
    from usplat_dr.model import UniqueSplat

    root = tmp_path / "data"
    synthesize(root, scenes=2, frames=10, resolution=(32, 32), seed=3, spp=4, stage="test",
               previews=0, progress=False, kinds=("indoor",))
    indices = synthetic_indices(root)
    assert "standard" in indices
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="baseline")
    dataset = {"name": "synth", "roots": [str(root)], "image_shape": [32, 32]}
    summary = evaluate(model, dataset, {"standard": indices["standard"]}, tmp_path / "eval",
                       progress=False)
    with open(tmp_path / "eval" / "per_scene.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 == summary["splits"]["standard"]["scenes"]
    # the split's PSNR is the mean over scenes of the per-scene means over targets
    assert summary["splits"]["standard"]["psnr"] == pytest.approx(
        sum(float(r["psnr"]) for r in rows) / 2, rel=1e-6)
    assert summary["splits"]["standard"]["lpips"].startswith("unavailable")
    assert 0 <= summary["splits"]["standard"]["delta1"] <= 1
    # recompute one scene's PSNR independently from its saved render inputs
    from usplat_dr.training import dataset_from_config, scene_args

    ds = dataset_from_config({**dataset, "evaluation_index": indices["standard"]}, "test")
    example = next(iter(ds))
    from torch.utils.data import default_collate

    batch = default_collate([example])
    with torch.no_grad():
        out = model.eval()(*scene_args(batch, torch.device("cpu")))
    per_target = psnr(out.color[0], batch["target"]["image"][0])
    assert float(rows[0]["psnr"]) == pytest.approx(per_target.mean().item(), rel=1e-5)
    assert (tmp_path / "eval" / "renders" / "standard" / f"{example['scene']}.png").is_file()
    saved = json.loads((tmp_path / "eval" / "summary.json").read_text())
    assert saved["parameters"] == sum(p.numel() for p in model.parameters())
    with pytest.raises(FileNotFoundError, match="usplat train writes"):
        load_model(tmp_path / "missing.ckpt")


def test_demo_quick_end_to_end(tmp_path):
    from usplat_dr.demo_job import SHIPPED, run_demo

    report = run_demo(tmp_path, "quick")  # from the shipped checkpoints (checkpoints/)
    text = report.read_text()
    assert "| (a) primary network `tiny_baseline_continued`" in text
    assert "| (c) UniqueSplat `tiny_full`" in text
    assert "## Verdict on view conditioning" in text and "| standard | psnr | (c) - (a) |" in text
    assert (tmp_path / "training_curves.png").is_file() and (tmp_path / "verdict.png").is_file()
    for variant in SHIPPED:
        s = json.loads((tmp_path / f"eval_shipped_{variant}" / "summary.json").read_text())
        assert s["variant"] == variant and math.isfinite(s["splits"]["standard"]["psnr"])
    for variant in ("baseline", "full"):  # the brief fine-tuning from the shipped (a)
        assert (tmp_path / f"train_{variant}" / "checkpoints" / "last.ckpt").is_file()
    assert "sha256" in text and "drjit" in text  # where the numbers came from
    images = [line for line in text.splitlines() if line.startswith("![")]
    assert all((tmp_path / line.split("(")[1].rstrip(")")).is_file() for line in images)

    # the fine-tuned (c) model's video and PLY export through the CLI
    from usplat_dr.cli import main

    ckpt = str(tmp_path / "train_full" / "checkpoints" / "last.ckpt")
    common = ["--checkpoint", ckpt, "--data", str(tmp_path / "data"), "--image-shape", "32",
              "32"]
    assert main(["-q", "render", *common, "--frames", "6", "--out",
                 str(tmp_path / "video")]) == 0
    assert list(tmp_path.glob("video.*"))
    assert main(["-q", "export-ply", *common, "--target", "1", "--out",
                 str(tmp_path / "g.ply")]) == 0
    from usplat_dr.ply import read_ply

    assert read_ply(tmp_path / "g.ply")["means"].shape == (2 * 32 * 32, 3)

    # the report's stress, bench and stability sections
    assert "### Worst cases" in text and "## Speed against accuracy" in text
    assert "view-specific H_s" in text  # gradient norms of the hypernetwork branches
    assert "Warning" not in text
    import csv

    with open(tmp_path / "bench_demo" / "bench.csv") as f:
        rows = list(csv.DictReader(f))
    by = {(r["config"], r["prune"], r["render_size"]): r for r in rows}
    assert len(by) == len(rows) == 2 * (6 + 1)  # 2 models x (6 budgets at 32 px + 16 px)
    for config in ("tiny (a)", "tiny (c)"):
        # exact culling: same PSNR (float32 summation order only)
        assert abs(float(by[(config, "cull", "32")]["psnr_change_db"])) < 1e-3
        assert float(by[(config, "keep25%", "32")]["kept_fraction"]) <= 0.25 + 1e-6
        assert float(by[(config, "cull", "32")]["gaussians_per_view"]) <= 2 * 32 * 32

    # `usplat bench` reuses the demo's trained runs (same folder) and adds nothing to train
    assert main(["-q", "bench", "--quick", "--out", str(tmp_path), "--configs",
                 "tiny:a,tiny:c", "--prunes", "all,cull", "--render-sizes", "32"]) == 0
    assert (tmp_path / "bench" / "bench.png").is_file()
    summary = json.loads((tmp_path / "bench" / "summary.json").read_text())
    assert summary["pruning"]["cull"]["safe"]
