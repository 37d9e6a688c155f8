"""train/studies/res128_ceiling.py: the split of the upsampled renders' error into the detail a
half-size image lacks and the small model's own errors, against numpy in float64 from the
definitions (the bicubic upsampling of the reference test of res128_eval.py)."""

import importlib.util
from pathlib import Path

import numpy as np
import torch

from tests.train.test_res128_eval import upsample_reference

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "res128_ceiling.py"
spec = importlib.util.spec_from_file_location("res128_ceiling", SCRIPT)
study = importlib.util.module_from_spec(spec)
spec.loader.exec_module(study)


def test_readings_match_their_definitions_in_float64():
    rng = np.random.default_rng(1)
    truth = rng.uniform(0.1, 0.9, size=(2, 3, 8, 6))
    truth_small = truth.reshape(2, 3, 4, 2, 3, 2).mean((3, 5))  # any half-size image
    pred = np.clip(truth_small + rng.normal(0, 0.05, truth_small.shape), 0, 1)
    got = study.decompose(*(torch.tensor(a, dtype=torch.float32)
                            for a in (pred, truth_small, truth)))
    up = np.stack([[upsample_reference(c, 2) for c in t] for t in pred])
    truth_up = np.stack([[upsample_reference(c, 2) for c in t] for t in truth_small])
    truth32 = truth.astype(np.float32).astype(np.float64)  # the inputs' float32 rounding
    err = ((up - truth32) ** 2).mean((1, 2, 3))
    res = ((truth_up - truth32) ** 2).mean((1, 2, 3))
    own = ((up - truth_up) ** 2).mean((1, 2, 3))
    ref = {"psnr_truth_up": np.mean(-10 * np.log10(res)),
           "psnr_small_up": np.mean(-10 * np.log10(err)),
           "psnr_small_vs_truth_up": np.mean(-10 * np.log10(own)),
           "cross": np.mean((err - res - own) / err)}
    ref["detail_gain"] = ref["psnr_small_vs_truth_up"] - ref["psnr_small_up"]
    for key, value in ref.items():
        # the upsampling runs in float32 (errors ~1e-7 on values of ~0.05 and MSEs of ~1e-3):
        # 1e-4 dB and 1e-4 of the MSE are far above that and far below any reading's use
        assert abs(got[key] - value) < 1e-4, key


def test_a_uniform_offset_is_the_models_own_error_whatever_the_detail():
    # bicubic weights sum to one: an offset of 0.05 everywhere stays 0.05 after upsampling, so
    # the renders against the upsampled truth read -10 log10(0.05^2) = 26.02 dB, whatever
    # detail the full-size truth has
    rng = np.random.default_rng(2)
    truth = torch.tensor(rng.uniform(0.2, 0.8, size=(1, 3, 8, 8)), dtype=torch.float32)
    truth_small = torch.full((1, 3, 4, 4), 0.5)
    got = study.decompose(truth_small + 0.05, truth_small, truth)
    assert abs(got["psnr_small_vs_truth_up"] - (-20 * np.log10(0.05))) < 1e-4
    assert got["detail_gain"] > 0  # removing the detail term can only help here
