"""train/studies/auto_content.py: its rank correlation is the Pearson correlation of the ranks
(computed here with NumPy, ties averaged), and the textured share counts the material code."""

import importlib.util
import math
from pathlib import Path

import numpy as np
import torch

from usplat_dr.data.synth.render import PLAIN, TEXTURED

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "auto_content.py"
spec = importlib.util.spec_from_file_location("auto_content", SCRIPT)
study = importlib.util.module_from_spec(spec)
spec.loader.exec_module(study)


def numpy_ranks(v):
    v = np.asarray(v, dtype=float)
    r = np.empty(len(v))
    for x in np.unique(v):  # average ranks over ties
        where = np.flatnonzero(v == x)
        r[where] = np.argsort(np.argsort(v, kind="stable"), kind="stable")[where].mean() + 1
    return r


def test_spearman_is_pearson_of_the_ranks():
    rng = np.random.default_rng(0)
    for ties in (False, True):
        x = rng.integers(0, 5, 30) if ties else rng.normal(size=30)
        y = x + rng.normal(size=30)
        expected = np.corrcoef(numpy_ranks(x), numpy_ranks(y))[0, 1]
        # float64 sums over 30 ranks on both sides: they agree to rounding
        assert math.isclose(study.spearman(list(x), list(y)), expected, abs_tol=1e-12)
    assert math.isnan(study.spearman([1, 1, 1], [1, 2, 3]))  # a constant side
    assert math.isnan(study.spearman([1, 2], [1, 2]))


def test_textured_share_counts_the_textured_code():
    material = torch.full((2, 4, 4), float(PLAIN))
    material[0, :2] = TEXTURED  # 8 of the 32 pixels
    assert study.textured_share(material) == 0.25
