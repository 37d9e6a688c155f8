"""The official MVSplat fixture (``tests/fixtures/mvsplat_fixture_dev.pt``, see its README) and
a network loaded with the deterministic weights it was made with."""

from pathlib import Path

import pytest
import torch

from tests.fixtures.deterministic_weights import deterministic_state_dict
from usplat_dr.model import PrimaryNetwork

FIXTURES = Path(__file__).parents[1] / "fixtures"
MANIFEST = FIXTURES / "mvsplat_re10k_state_dict.tsv"


@pytest.fixture(scope="session")
def fixture_dev() -> dict:
    return torch.load(FIXTURES / "mvsplat_fixture_dev.pt", weights_only=True)


@pytest.fixture(scope="session")
def weights() -> dict:
    """The deterministic weights, ``encoder.`` prefix stripped."""
    return deterministic_state_dict(str(MANIFEST), strip_prefix="encoder.")


@pytest.fixture(scope="session")
def net(weights) -> PrimaryNetwork:
    net = PrimaryNetwork().eval()
    net.load_state_dict(weights, strict=True)
    return net


def inputs(fx: dict) -> tuple:
    return tuple(fx[k] for k in ("images", "extrinsics", "intrinsics", "near", "far"))


def two_view_cameras(b: int = 1, v: int = 2, baseline: float = 0.1):
    """Cameras side by side along x, looking down +z, the fixture's intrinsics:
    (extrinsics, intrinsics)."""
    e = torch.eye(4).repeat(b, v, 1, 1)
    e[:, :, 0, 3] = baseline * torch.arange(v, dtype=torch.float32)
    k = torch.tensor([[0.85, 0, 0.5], [0, 0.85, 0.5], [0, 0, 1]]).repeat(b, v, 1, 1)
    return e, k
