"""Shared fixtures: the ``backend`` fixture runs LLVM always and CUDA where a GPU is present."""

import os

import pytest
import torch

import usplat_dr  # noqa: F401  (chooses libLLVM before anything imports drjit)
from usplat_dr import portable


def _cuda_available() -> bool:
    if not torch.cuda.is_available():
        return False
    import drjit as dr

    return dr.has_backend(dr.JitBackend.CUDA)


BACKENDS = ["llvm"] + (["cuda"] if _cuda_available() else [])


@pytest.fixture(params=BACKENDS)
def backend(request) -> str:
    """'llvm' (CPU tensors) or 'cuda' (CUDA tensors)."""
    return request.param


@pytest.fixture
def device(backend) -> torch.device:
    return torch.device("cpu" if backend == "llvm" else "cuda")


@pytest.fixture
def restore_threads():
    """Trainer sets the process's torch and Dr.Jit thread counts; put them back."""
    import drjit as dr

    torch_threads, dr_threads = torch.get_num_threads(), dr.thread_count()
    yield
    torch.set_num_threads(torch_threads)
    dr.set_thread_count(dr_threads)


@pytest.fixture(autouse=True)
def _flush_denormals():
    # exp() of large negative powers in the dense reference gives denormals, which make float64
    # CPU arithmetic ~2x slower without changing any result we compare.
    torch.set_flush_denormal(True)
    yield


@pytest.fixture(autouse=True)
def _restore_environment():
    # In-process `usplat` calls (cli.main) turn portable numerics on by writing os.environ;
    # later tests' subprocesses (torchrun workers) would otherwise inherit them.
    # Dr.Jit's pinned LLVM target stays in the process too: Mitsuba would then render the
    # synthetic sets of later tests with other kernels than their worker processes do.
    saved = dict(os.environ)
    yield
    if os.environ != saved:
        os.environ.clear()
        os.environ.update(saved)
        if not portable.enabled():
            portable.unpin_drjit()


@pytest.fixture(scope="session")
def synthetic_sets(tmp_path_factory):
    """``get(name)``: the named set of ``tests/synth_sets.py``, rendered once per test run.
    Read only: a test that writes into a set renders its own."""
    from tests.synth_sets import synthetic_set

    made = {}

    def get(name: str):
        if name not in made:
            made[name] = synthetic_set(name, tmp_path_factory.mktemp(f"set_{name}"))
        return made[name]

    return get


@pytest.fixture(scope="session")
def trainer_set(synthetic_sets):
    """Two training scenes (seed 0) and two test scenes (seed 1), 10 frames of 32x32."""
    return synthetic_sets("trainer")


@pytest.fixture(scope="session")
def protocol_set(synthetic_sets):
    """Two test scenes (seed 3) with the evaluation indices, 10 frames of 32x32."""
    return synthetic_sets("protocol")


@pytest.fixture(scope="module")
def user_scene(tmp_path_factory):
    """A user's own scene: the synthetic truth of tests/data/test_importers.py (images with
    known cameras) as a binary COLMAP model (sparse/0) and a transforms.json."""
    from tests.data.test_importers import Truth  # a test module: only when a test asks

    t = Truth(tmp_path_factory.mktemp("scene"))
    t.write_colmap_binary(t.root / "sparse" / "0")
    t.write_nerfstudio()
    return t

