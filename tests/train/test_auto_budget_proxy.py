"""train/studies/auto_budget_proxy.py: the proxy and real losses are the PSNR differences the
study defines, context views against their own images, targets against theirs."""

import importlib.util
import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from usplat_dr.model.auto_budget import Calibration

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "auto_budget_proxy.py"
spec = importlib.util.spec_from_file_location("auto_budget_proxy", SCRIPT)
study = importlib.util.module_from_spec(spec)
spec.loader.exec_module(study)


class Stub:
    """Renders a camera set as its reference image off by a known constant: 0.01 with every
    Gaussian; with a budget keeping f, 0.01 + (1 - f) / 10 on context views and 0.01 + (1 - f)
    / 20 on targets."""

    def __init__(self, context_image, target_image):
        self.context_image, self.target_image = context_image, target_image

    def encode(self, *args):
        return None

    def __call__(self, images, context, cameras, hooks=None, budget=None):
        is_context = cameras is context
        reference = self.context_image if is_context else self.target_image
        error = 0.01 + (0.0 if budget is None else (1 - budget.keep) / (10 if is_context else 20))
        return SimpleNamespace(color=reference + error)


def test_the_losses_are_the_psnr_differences():
    images = torch.full((1, 2, 3, 4, 4), 0.5)
    target = torch.full((1, 1, 3, 4, 4), 0.5)
    cams = SimpleNamespace(extrinsics=None, intrinsics=None, near=None, far=None)
    x = SimpleNamespace(images=images, context=cams, targets=SimpleNamespace())
    found = study.losses(Stub(images, target), x, target, (0.5,), "dither")
    # a constant error e gives PSNR -20 log10(e); float32 images: 1e-4 dB is ~10 ulp of 40 dB
    proxy, real = found[0.5]
    assert math.isclose(proxy, 20 * math.log10(0.06 / 0.01), abs_tol=1e-4)
    assert math.isclose(real, 20 * math.log10(0.035 / 0.01), abs_tol=1e-4)
    assert found[1.0] == (0.0, 0.0)


def write_proxy_csv(path, per_scene):
    import csv
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, study.FIELDS)
        w.writeheader()
        for scene, found in per_scene.items():
            for keep, (proxy, real) in found.items():
                w.writerow({"scene": scene, "keep": keep, "proxy_loss": proxy, "real_loss": real})


def test_the_calibration_line_and_margin_match_numpy():
    import numpy as np
    rng = np.random.default_rng(0)
    per_scene = {}
    for k in range(12):
        proxy = {keep: float(rng.uniform(0, 5) * (1 - keep)) for keep in (0.3, 0.5)}
        per_scene[f"indoor_{k:03d}"] = {
            1.0: (0.0, 0.0),
            **{keep: (p, 0.1 + 0.2 * p + float(rng.normal(0, 0.05))) for keep, p in proxy.items()}}
    calibration = Calibration.fit(per_scene, 0.9, "dither", "dev")
    fits = {row[0]: row[1:] for row in calibration.fits}
    for keep in (0.3, 0.5):
        x = np.array([f[keep][0] for f in per_scene.values()])
        y = np.array([f[keep][1] for f in per_scene.values()])
        slope, intercept = np.polyfit(x, y, 1)  # an independent least-squares fit
        margin = np.quantile(y - (intercept + slope * x), 0.9)
        # float64 on both sides: the two solvers agree to rounding
        assert np.allclose(fits[keep], (intercept, slope, margin), atol=1e-9)
    assert sorted(fits) == [0.3, 0.5]  # no line for keeping everything


def test_the_calibrated_count_keeps_the_smallest_budget_predicted_within_tolerance():
    fits = Calibration("dither", ((0.1, 0.5, 1.0, 0.1), (0.3, 0.0, 0.5, 0.05),
                                  (0.5, 0.0, 0.1, 0.0)), 0.9, "dev")
    found = {0.1: (1.0, 9.0), 0.3: (0.2, 9.0), 0.5: (0.1, 9.0), 1.0: (0.0, 0.0)}
    # predicted: 0.1 -> 1.6, 0.3 -> 0.15, 0.5 -> 0.01
    assert study.calibrated_choice(found, fits, 0.2) == 0.3
    assert study.calibrated_choice(found, fits, 0.05) == 0.5
    assert study.calibrated_choice(found, fits, 0.001) == 1.0  # none predicted within: all


def test_main_reads_a_calibration_and_reports_per_kind(tmp_path, capsys):
    import json
    cal = {f"object_{k:03d}": {1.0: (0.0, 0.0), 0.5: (float(k), 0.1 * k)} for k in range(5)}
    write_proxy_csv(tmp_path / "cal.csv", cal)
    out = tmp_path / "out"
    out.mkdir()
    held = {"indoor_000": {1.0: (0.0, 0.0), 0.5: (1.0, 0.1)},
            "outdoor_000": {1.0: (0.0, 0.0), 0.5: (4.0, 0.4)}}
    write_proxy_csv(out / "proxy.csv", held)
    assert study.main(["--data", "unused", "--reuse", "--calibration", str(tmp_path / "cal.csv"),
                       "--out", str(out)]) == 0
    rows = json.loads((out / "summary.json").read_text())["rows"]
    # the line through the calibration is real = 0.1 proxy exactly (margin 0): at 0.2 dB the
    # indoor scene (predicted 0.1) keeps half, the outdoor one (0.4) keeps all
    got = rows["calibrated"]["0.2"]
    assert got["chosen"] == {"indoor_000": 0.5, "outdoor_000": 1.0}
    assert got["mean_kept_by_kind"] == {"indoor": 0.5, "outdoor": 1.0}
    assert "outdoor 100% (1)" in capsys.readouterr().out


def test_ship_records_the_calibration_in_the_manifest_entry(tmp_path):
    import json
    manifest = [{"name": "a", "file": "a.pt"},
                {"name": "b", "file": "b.pt", "auto_budget": [
                    {"rank_by": "dither", "quantile": 0.9, "data": "old", "fits": []},
                    {"rank_by": "learned", "quantile": 0.9, "data": "kept", "fits": []}]}]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    cal = Calibration("dither", ((0.5, 0.1, 0.2, 0.3),), 0.9, "dev")
    study.ship("b", cal, root=tmp_path)
    entries = json.loads((tmp_path / "manifest.json").read_text())
    assert "auto_budget" not in entries[0]
    # the dither calibration replaced, the learned one left as it was
    got = {d["rank_by"]: d for d in entries[1]["auto_budget"]}
    assert got["learned"]["data"] == "kept"
    assert Calibration.from_dict(got["dither"]) == cal
    with pytest.raises(ValueError, match="--ship nope: no such entry"):
        study.ship("nope", cal, root=tmp_path)


def test_a_calibration_of_another_model_or_ranking_is_refused(tmp_path, capsys):
    import json
    cal_dir = tmp_path / "cal"
    cal_dir.mkdir()
    write_proxy_csv(cal_dir / "proxy.csv", {f"object_{k:03d}": {1.0: (0.0, 0.0), 0.5: (k, k)}
                                            for k in range(4)})
    (cal_dir / "summary.json").write_text(json.dumps({"checkpoint": "tiny_full",
                                                      "rank_by": "dither"}))
    out = tmp_path / "out"
    for extra, needle in ((["--checkpoint", "tiny_full", "--rank-by", "learned"],
                           "rank_by 'dither', not 'learned'"),
                          (["--checkpoint", "tiny_full", "--ship", "tiny_full_budget"],
                           "checkpoint 'tiny_full', not 'tiny_full_budget'")):
        with pytest.raises(SystemExit):
            study.main(["--data", "unused", "--reuse", "--calibration",
                        str(cal_dir / "proxy.csv"), "--out", str(out), *extra])
        assert needle in capsys.readouterr().err


def test_the_size_defaults_to_the_checkpoints_training_size():
    # a 128x128 model calibrated at 64x64 would record a calibration for renders it never makes
    assert study.image_size("tiny_baseline_128", None) == 128
    assert study.image_size("tiny_full", None) == 64
    assert study.image_size("tiny_full_128", 64) == 64  # as given
