"""Where a result came from: the data's content hash, library versions, the CPU and thread
settings. Recorded in every training checkpoint and in the demo's report, so that two runs
that differ can be told apart by what they ran on (docs/reproducibility.md).

Examples:
    >>> info = environment()
    >>> sorted(info)[:3]
    ['cpu', 'drjit', 'mitsuba']
"""

import hashlib
import os
import platform
from importlib import metadata
from pathlib import Path

import torch

from usplat_dr import portable

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
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def provenance(roots=()) -> dict:
    """``environment()`` plus the content hash of each dataset root that exists."""
    return {**environment(),
            "data": {str(r): dataset_hash(r) for r in roots if Path(r).is_dir()}}
