"""Where a Gaussian budget goes (evaluation/allocation.py): the kept fraction by material and
depth against sums written out by hand, and what ``evaluate(budget=...)`` writes."""

import csv
import logging
import math

import pytest
import torch

from usplat_dr.data.synth.render import MISS, PLAIN, TEXTURED
from usplat_dr.evaluation import evaluate, synthetic_indices
from usplat_dr.evaluation.allocation import COLUMNS, allocation, kept_per_pixel


def test_kept_per_pixel_averages_targets_in_the_gaussians_order():
    # 3 targets, 2 views of 2x3 pixels: G = 12 in the order (view, row, column)
    mask = torch.zeros(3, 12, dtype=torch.bool)
    mask[:, 0] = True  # view 0, pixel (0, 0): kept by every target
    mask[0, 11] = True  # view 1, pixel (1, 2): kept by one of three
    kept = kept_per_pixel(mask, 2, 2, 3)
    assert kept.shape == (2, 2, 3)
    assert kept[0, 0, 0] == 1 and kept[1, 1, 2] == pytest.approx(1 / 3)
    assert kept.sum() == pytest.approx(1 + 1 / 3)
    with pytest.raises(ValueError, match="kept_mask"):
        kept_per_pixel(mask, 2, 2, 2)


def test_allocation_splits_the_kept_fraction_by_material_and_depth():
    # one view of 2x4 pixels: textured left half, plain right half (one pixel a miss, as
    # resizing leaves a blended code 1.2 on another); depths 1..8, one miss (+inf)
    kept = torch.tensor([[[1.0, 1.0, 0.0, 0.5], [1.0, 0.0, 0.0, 0.0]]])
    material = torch.tensor([[[TEXTURED, 1.2, PLAIN, PLAIN], [TEXTURED, TEXTURED, PLAIN,
                                                               MISS]]]).float()
    depth = torch.tensor([[[1.0, 2.0, 3.0, 4.0], [5.0, 6.0, 7.0, math.inf]]])
    a = allocation(kept, material, depth)
    assert set(a) == set(COLUMNS)
    assert a["kept"] == pytest.approx(3.5 / 8)
    assert a["kept_textured"] == pytest.approx((1 + 1 + 1 + 0) / 4)  # 1.2 rounds to textured
    assert a["kept_plain"] == pytest.approx((0 + 0.5 + 0) / 3)
    assert math.isnan(a["kept_glossy"])  # none in this scene
    # finite depths 1..7: median 4; near {1, 2, 3, 4} -> 1, 1, 0, 0.5; far {5, 6, 7}
    assert a["kept_near"] == pytest.approx(2.5 / 4) and a["kept_far"] == pytest.approx(1 / 3)
    assert set(allocation(kept)) == {"kept"}  # no maps, no splits


def test_evaluate_with_a_budget_says_where_it_went(tmp_path, caplog, protocol_set):
    from usplat_dr.model import UniqueSplat

    caplog.set_level(logging.ERROR, logger="usplat_dr.model.uniquesplat")
    root = protocol_set
    indices = synthetic_indices(root)
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="baseline")
    dataset = {"name": "synth", "roots": [str(root)], "image_shape": [32, 32]}
    summary = evaluate(model, dataset, {"standard": indices["standard"]}, tmp_path / "eval",
                       progress=False, budget=0.25)
    assert summary["gaussians"] == 0.25 and summary["rank_by"] == "dither"
    split = summary["splits"]["standard"]
    assert split["allocation"]["all"]["kept"] == pytest.approx(0.25, abs=1e-3)
    kinds = {r.split("_")[0] for r in split["allocation"]} - {"all"}
    assert kinds and kinds <= {"indoor", "outdoor", "object"}
    with open(tmp_path / "eval" / "per_scene.csv") as f:
        rows = list(csv.DictReader(f))
    assert {"kept", "kept_textured", "kept_near", "kept_far"} <= set(rows[0])
    assert all(float(r["kept"]) == pytest.approx(0.25, abs=1e-3) for r in rows)
    assert len(list((tmp_path / "eval" / "allocation" / "standard").glob("*.png"))) == len(rows)
