"""The tile sort keeps each tile's pairs in the order they were generated (depth order), on
every backend."""

import numpy as np
import pytest

from usplat_dr import backend as backends
from usplat_dr.render.binning import stable_bucket_order


@pytest.mark.parametrize("size", [1_000, 300_000, 3_000_000])
def test_bucket_order_matches_numpys_stable_argsort(backend, size):
    # Dr.Jit's CUDA block_mkperm broke the order within buckets from ~300,000 entries on an
    # H200; 3,000,000 entries span many blocks on any GPU. NumPy's stable argsort is the
    # independent reference: the permutation must equal it exactly.
    m = backends.module_for(backend)
    values = np.random.default_rng(size).integers(0, 4096, size, dtype=np.uint32)
    perm = stable_bucket_order(m.UInt32(values), size, 4096).numpy()
    np.testing.assert_array_equal(perm, np.argsort(values, kind="stable"))
