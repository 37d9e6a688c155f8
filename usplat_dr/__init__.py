"""usplat-dr: UniqueSplat with a Dr.Jit Gaussian rasteriser.

Importing this package first points Dr.Jit at a safe libLLVM (see ``usplat_dr._llvm``) and
shortens torch's OpenMP spin-waiting (``usplat_dr._threads``), so it must stay free of
drjit/mitsuba/torch imports at module level: subpackages import them lazily.
"""

from usplat_dr import _llvm, _threads

_llvm.configure()
_threads.configure()

__version__ = "0.1.0"

#: How long ``usplat demo`` takes on 2 CPU cores from a fresh clone (installation excluded), the
#: range over the machine kinds it ran on (BENCHMARKS.md, "the demo"): stated once, read by the
#: CLI's help and ``jobs/demo.py``, and checked against the README by a test.
DEMO_MINUTES = "4-14"


def __getattr__(name: str):
    """``usplat_dr.load``: ``usplat_dr.training.loader.load`` (a model from a shipped
    checkpoint's name, a training checkpoint or an MVSplat file), imported on first use so
    that importing the package stays free of torch."""
    if name == "load":
        # lazy: the package must import before torch (see above); training needs torch
        from usplat_dr.training.loader import load
        return load
    raise AttributeError(f"module 'usplat_dr' has no attribute {name!r}")

