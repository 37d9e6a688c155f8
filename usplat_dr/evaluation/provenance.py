"""Where a result came from: the data's content hash, library versions, the CPU and thread
settings. Recorded in every training checkpoint and in the demo's report, so that two runs
that differ can be told apart by what they ran on (docs/reproducibility.md). Training
checkpoints also record the keys of the scenes they trained on (``training_keys``), so that
``usplat eval`` can warn when it scores one of them (``keys_in_training``).

Examples:
    >>> info = environment()
    >>> sorted(info)[:3]
    ['cores', 'cpu', 'drjit']
"""

import hashlib
import os
import platform
from importlib import metadata
from pathlib import Path

import torch

from usplat_dr import portable
from usplat_dr.data.chunks import read_index
from usplat_dr.io.user_files import sha256

#: Files that define a dataset's content: chunks, their index and the evaluation indices.
DATA_PATTERNS = ("*/index.json", "*/*.torch", "evaluation_index_*.json")


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), or ``platform.processor()`` elsewhere."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def environment() -> dict:
    """Library versions, the CPU model, core count and the thread settings in force."""
    info = {"python": platform.python_version(), "cpu": cpu_model(),
            "cores": os.cpu_count(), "torch_threads": torch.get_num_threads()}
    for package in ("torch", "drjit", "mitsuba", "numpy"):
        info[package] = _version(package)
    info["numerics"] = portable.describe()
    return info


#: Bytes one dataset file may hold when hashed (the field's chunks are about 100 MB).
MAX_DATASET_FILE_BYTES = 16 * 2**30


def dataset_hash(root: str | os.PathLike) -> str:
    """SHA-256 over a dataset folder's chunk files, ``index.json`` files and evaluation
    indices (relative path and bytes, in sorted order): equal hashes mean the same data."""
    root = Path(root)
    files = sorted({p for pattern in DATA_PATTERNS for p in root.glob(pattern)})
    if not files:
        raise FileNotFoundError(f"{root} holds no dataset files ({', '.join(DATA_PATTERNS)})")
    h = hashlib.sha256()
    for p in files:
        h.update(p.relative_to(root).as_posix().encode() + b"\0")
        sha256(p, "dataset file", MAX_DATASET_FILE_BYTES, digest=h)  # a FIFO: refused
    return h.hexdigest()


def training_keys(roots=()) -> list[str]:
    """The sorted scene keys of the train stage (``<root>/train/index.json``) of each root
    that has one: what a training run saw (checkpoints record them as ``train_keys``)."""
    keys: set[str] = set()
    for root in roots:
        if (Path(root) / "train" / "index.json").is_file():
            keys.update(read_index(Path(root) / "train"))
    return sorted(keys)


def keys_in_training(scored, provenance_record: dict) -> list[str] | None:
    """The scored scene keys that a checkpoint's provenance (``provenance_record``) lists as
    training scenes, sorted; ``None`` when it records none (checkpoints from before
    ``train_keys``: nothing to check against).

    Examples:
        >>> keys_in_training(["a", "b"], {"train_keys": ["b", "c"]})
        ['b']
        >>> keys_in_training(["a"], {"data": {}}) is None
        True
    """
    train = provenance_record.get("train_keys") if isinstance(provenance_record, dict) else None
    if not isinstance(train, (list, tuple)):
        return None
    return sorted(set(scored) & set(train))


def provenance(roots=()) -> dict:
    """``environment()`` plus the content hash of each dataset root that exists."""
    return {**environment(),
            "data": {str(r): dataset_hash(r) for r in roots if Path(r).is_dir()}}
