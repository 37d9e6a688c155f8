"""How a failing rank is reported (``rank_failure``), without starting processes: the store
that the ranks of a torchrun job share is a ``HashStore`` here."""

import json

import pytest
import torch.distributed as dist

from usplat_dr.training import distributed
from usplat_dr.training.distributed import rank_failure


@pytest.fixture
def shared_store(monkeypatch):
    store = dist.HashStore()
    monkeypatch.setattr(distributed, "_store", lambda: store)
    return store


def test_the_first_failure_is_every_ranks_message(shared_store, tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHELASTIC_ERROR_FILE", str(tmp_path / "error1.json"))
    first = rank_failure(ValueError("chunk 3 is corrupt"), rank=1, world=2, step=7)
    assert first.own
    assert str(first) == "rank 1 of 2 failed at step 7: ValueError: chunk 3 is corrupt"
    # rank 0's collective then breaks: it takes rank 1's message, not its own error
    monkeypatch.setenv("TORCHELASTIC_ERROR_FILE", str(tmp_path / "error0.json"))
    second = rank_failure(RuntimeError("Connection closed by peer"), rank=0, world=2, step=7)
    assert not second.own and str(second) == str(first)
    for name in ("error1.json", "error0.json"):  # torchrun's summary prints these
        data = json.loads((tmp_path / name).read_text())
        assert data["message"]["message"] == str(first)


def test_without_a_store_the_failure_is_this_ranks(monkeypatch, tmp_path):
    monkeypatch.setattr(distributed, "_store", lambda: None)  # failed before the group existed
    monkeypatch.delenv("TORCHELASTIC_ERROR_FILE", raising=False)
    failure = rank_failure(KeyError("dataset"), rank=3, world=4, step=None)
    assert failure.own and str(failure) == "rank 3 of 4 failed: KeyError: 'dataset'"


class _OnAnotherDevice:
    """A stand-in for a CUDA generator state read back with map_location="cuda": torch's
    setter accepts only the CPU ByteTensor that ``.cpu()`` gives."""

    def __init__(self, state):
        self.state = state

    def cpu(self):
        return self.state


def test_a_cuda_rng_state_read_onto_the_gpu_is_restored_from_the_cpu(monkeypatch):
    # --resume of a run on a GPU failed with "RNG state must be a torch.ByteTensor": the
    # checkpoint, loaded onto the GPU, held the CUDA generators' states there.
    import torch

    byte_state = torch.zeros(16, dtype=torch.uint8)
    state = {k: v for k, v in distributed.rng_state().items() if k != "cuda"}
    state["cuda"] = [_OnAnotherDevice(byte_state)]
    given = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "set_rng_state_all", given.extend)
    distributed.set_rng_state(state)
    assert len(given) == 1 and given[0] is byte_state
