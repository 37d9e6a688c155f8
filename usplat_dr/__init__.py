"""usplat-dr: UniqueSplat with a Dr.Jit Gaussian rasteriser.

Importing this package first points Dr.Jit at a safe libLLVM (see ``usplat_dr._llvm``), so it
must stay free of drjit/mitsuba/torch imports at module level: subpackages import them lazily.
"""

from usplat_dr import _llvm

_llvm.configure()

__version__ = "0.1.0"
