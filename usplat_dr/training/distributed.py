"""Processes and random state: rank, world size and device under ``torchrun`` (gloo on CPU,
nccl on GPU), threads per rank, the RNG states a checkpoint saves, and how a run ends when one
of its ranks fails.

A failing rank must end the whole run with one message naming it and the cause, not with the
others' collective errors ("Connection closed by peer"). ``rank_failure`` is called on every
rank whose training raised: the first posts its message in the process group's store (the
torchrun agent's, which outlives the workers) before it exits, so a rank whose collective then
breaks finds the message there and stops quietly; both write it to torchrun's error file
(``TORCHELASTIC_ERROR_FILE``), which torchrun's closing summary prints.
"""

import hashlib
import json
import logging
import os
import random
import time

import drjit as dr
import numpy as np
import torch
import torch.distributed as dist

from usplat_dr import _threads
from usplat_dr.backend import require_llvm
from usplat_dr.config import ConfigError

log = logging.getLogger(__name__)


def setup_distributed(device: str, threads: int | None = None
                      ) -> tuple[int, int, torch.device]:
    """Rank, world size and device; initialises the process group under torchrun. CPU threads
    of torch and Dr.Jit per process: ``threads``; else, for one process, one per free core
    (``usplat_dr._threads.choose``: ``USPLAT_THREADS``, or the allowed cores less those other
    processes keep busy), and under torchrun the allowed cores divided by this machine's
    ranks."""
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
    # Share the machine's cores between its ranks (torchrun's LOCAL_WORLD_SIZE; not all ranks
    # of a multi-node run) so they do not oversubscribe them.
    ranks_here = int(os.environ.get("LOCAL_WORLD_SIZE", str(world)))
    if threads:
        why = "the threads setting"
    elif ranks_here > 1:  # the other ranks are this run's: share the cores, not the load
        threads = max(1, _threads.allowed_cores() // ranks_here)
        why = f"{_threads.allowed_cores()} core(s) allowed / {ranks_here} ranks"
    else:
        choice = _threads.choose()
        threads, why = choice.threads, choice.why
    if device == "cpu":
        log.info("threads: %d (%s)", threads, why)
    set_threads(threads, device)
    return rank, world, dev


def set_threads(threads: int, device: str = "cpu") -> None:
    """torch's intra-op threads, and on the CPU Dr.Jit's LLVM pool, to ``threads``."""
    torch.set_num_threads(threads)
    if device == "cpu":
        require_llvm()  # pins Dr.Jit's target now (USPLAT_PORTABLE), before any kernel
        dr.set_thread_count(threads)


def set_tf32(tf32: bool | None) -> None:
    """cuDNN convolutions and CUDA matrix products in TF32 (``True``), in IEEE float32
    (``False``), or as torch leaves them (``None``). Through torch's per-backend
    ``fp32_precision`` switches where they exist (torch >= 2.9), else the older ``allow_tf32``
    flags (mixing the two is an error in torch)."""
    if tf32 is None:
        return
    precision = "tf32" if tf32 else "ieee"
    conv = getattr(torch.backends.cudnn, "conv", None)
    if conv is not None and hasattr(conv, "fp32_precision"):
        conv.fp32_precision = precision
        torch.backends.cuda.matmul.fp32_precision = precision
    else:
        torch.backends.cudnn.allow_tf32 = tf32
        torch.backends.cuda.matmul.allow_tf32 = tf32


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
        # a checkpoint read with map_location="cuda" holds them on the GPU; torch takes CPU
        # ByteTensors only ("RNG state must be a torch.ByteTensor" on --resume otherwise)
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])


def gather(obj: object) -> list:
    """Every rank's ``obj`` in rank order (``[obj]`` outside a process group). A collective:
    every rank must call it at the same point."""
    if not (dist.is_available() and dist.is_initialized()):
        return [obj]
    out = [None] * dist.get_world_size()
    dist.all_gather_object(out, obj)
    return out


def parameter_digest(model: torch.nn.Module) -> str:
    """A short SHA-256 of the model's parameters (names and bytes, not buffers): equal digests,
    equal weights. Under DDP every rank must end with the same one (``Trainer.fit`` checks).

    Examples:
        >>> a, b = torch.nn.Linear(2, 1), torch.nn.Linear(2, 1)
        >>> b.load_state_dict(a.state_dict())
        <All keys matched successfully>
        >>> parameter_digest(a) == parameter_digest(b), len(parameter_digest(a))
        (True, 16)
    """
    h = hashlib.sha256()
    for name, p in model.named_parameters():
        h.update(name.encode())
        h.update(p.detach().cpu().reshape(-1).contiguous().view(torch.uint8).numpy().tobytes())
    return h.hexdigest()[:16]


class RankFailed(RuntimeError):
    """A rank of a distributed run failed. The message names the rank and the cause; ``own``
    is true on the failing rank, false on a rank that stopped because of it."""

    def __init__(self, message: str, own: bool):
        super().__init__(message)
        self.own = own


def _failure_key() -> str:
    # a new key for each torchrun restart (the agent's store outlives the workers)
    return f"usplat/failure/{os.environ.get('TORCHELASTIC_RESTART_COUNT', '0')}"


def _store():
    if not (dist.is_available() and dist.is_initialized()):
        return None
    try:
        return dist.distributed_c10d._get_default_store()
    except (RuntimeError, ValueError):
        return None


def _write_error_file(message: str, timestamp: int) -> None:
    """torchrun's error file (the format of torch.distributed.elastic's ``record``), so that its
    summary shows ``message`` instead of "To enable traceback see ..."."""
    path = os.environ.get("TORCHELASTIC_ERROR_FILE")
    if not path:
        return
    data = {"message": {"message": message, "extraInfo": {"timestamp": str(timestamp)}}}
    try:
        with open(path, "w") as f:
            json.dump(data, f)
    except OSError as e:
        log.warning("cannot write torchrun's error file %s: %s", path, e)


def rank_failure(exc: BaseException, rank: int, world: int, step: int | None) -> RankFailed:
    """What ends this rank after ``exc`` in a run of ``world`` ranks: the failure another rank
    posted first (``own`` false: this rank's error is the broken collective that followed),
    else this rank's own, posted for the others (first come, first posted: the store's
    compare-and-set). ``step``: where it happened, when known."""
    at = f" at step {step}" if step is not None else ""
    mine = {"rank": rank, "message": f"rank {rank} of {world} failed{at}: "
            f"{type(exc).__name__}: {exc}", "timestamp": int(time.time())}
    posted = mine
    store = _store()
    if store is not None:
        try:
            posted = json.loads(store.compare_set(_failure_key(), "", json.dumps(mine)))
        except (RuntimeError, ValueError) as e:  # the store went with its host (rank 0)
            log.debug("cannot reach the process group's store: %s", e)
    _write_error_file(posted["message"], posted["timestamp"])
    return RankFailed(posted["message"], own=posted["rank"] == rank)
