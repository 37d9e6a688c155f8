"""Processes and random state: rank, world size and device under ``torchrun`` (gloo on CPU,
nccl on GPU), threads per rank, and the RNG states a checkpoint saves."""

import os
import random

import drjit as dr
import numpy as np
import torch
import torch.distributed as dist

from usplat_dr.backend import require_llvm
from usplat_dr.config import ConfigError


def setup_distributed(device: str, threads: int | None = None
                      ) -> tuple[int, int, torch.device]:
    """Rank, world size and device; initialises the process group under torchrun. CPU threads
    of torch and Dr.Jit per process: ``threads``, or the cores divided by the ranks."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    if device == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError("device=cuda but torch sees no GPU; use device=cpu")
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local)
        dev = torch.device("cuda", local)
    elif device == "cpu":
        dev = torch.device("cpu")
    else:
        raise ConfigError(f"device must be 'cpu' or 'cuda', got {device!r}")
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device == "cuda" else "gloo")
    # Share the cores between ranks so they do not oversubscribe them.
    threads = threads or max(1, (os.cpu_count() or 1) // world)
    torch.set_num_threads(threads)
    if device == "cpu":
        require_llvm()  # pins Dr.Jit's target now (USPLAT_PORTABLE), before any kernel
        dr.set_thread_count(threads)
    return rank, world, dev


def rng_state() -> dict:
    """The random number generators' states (torch, NumPy, Python, CUDA), for checkpoints, as
    tensors and plain data (so a checkpoint loads with ``torch.load(weights_only=True)``)."""
    kind, keys, pos, has_gauss, gauss = np.random.get_state()
    state = {"torch": torch.get_rng_state(),
             "numpy": {"kind": str(kind), "keys": torch.from_numpy(keys.astype(np.int64)),
                       "pos": int(pos), "has_gauss": int(has_gauss), "gauss": float(gauss)},
             "python": random.getstate()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    """Restore ``rng_state()``'s states."""
    torch.set_rng_state(state["torch"].cpu())
    npy = state["numpy"]
    if isinstance(npy, dict):
        npy = (npy["kind"], npy["keys"].cpu().numpy().astype(np.uint32), npy["pos"],
               npy["has_gauss"], npy["gauss"])
    np.random.set_state(npy)  # (a tuple in checkpoints written before the dict form)
    random.setstate(state["python"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
