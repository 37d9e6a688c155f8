"""usplat-dr: UniqueSplat with a Dr.Jit Gaussian rasteriser.

Importing this package first points Dr.Jit at a safe libLLVM (see ``usplat_dr._llvm``) and
shortens torch's OpenMP spin-waiting (``usplat_dr._openmp``), so it must stay free of
drjit/mitsuba/torch imports at module level: subpackages import them lazily.
"""

from usplat_dr import _llvm, _openmp

_llvm.configure()
_openmp.configure()

__version__ = "0.1.0"
