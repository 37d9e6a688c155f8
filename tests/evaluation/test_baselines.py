import numpy as np
import torch

from usplat_dr.evaluation.baselines import copy_nearest, nearest_context


def _poses(centres: np.ndarray) -> torch.Tensor:
    e = torch.eye(4, dtype=torch.float64).repeat(len(centres), 1, 1)
    e[:, :3, 3] = torch.from_numpy(centres)
    return e.float()


def test_nearest_context_matches_a_loop_over_camera_centres():
    rng = np.random.default_rng(0)
    ctx, tgt = rng.normal(size=(3, 3)), rng.normal(size=(20, 3))
    rotated = _poses(ctx)
    rotated[:, :3, :3] = torch.linalg.qr(torch.randn(3, 3, 3))[0]  # rotations play no part
    ref = [int(np.argmin([np.linalg.norm(t - c) for c in ctx])) for t in tgt]
    assert nearest_context(rotated, _poses(tgt)).tolist() == ref


def test_copy_nearest_returns_the_nearest_context_image():
    images = torch.rand(2, 3, 4, 5)
    ctx = _poses(np.array([[0.0, 0, 0], [1.0, 0, 0]]))
    tgt = _poses(np.array([[0.9, 0, 0], [0.2, 0.1, 0], [1.0, 0, 0]]))
    out = copy_nearest(images, ctx, tgt)
    assert torch.equal(out, images[[1, 0, 1]])
