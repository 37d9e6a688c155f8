"""Dr.Jit backend selection: the backend follows the inputs.

CPU torch tensors run on ``drjit.llvm.ad`` and CUDA tensors on ``drjit.cuda.ad``; Dr.Jit arrays
carry their backend in their type. This module imports drjit (after ``usplat_dr`` chose libLLVM)
but never torch or Mitsuba.
"""

import types

import drjit as dr

from usplat_dr import _llvm, portable


def require_llvm() -> types.ModuleType:
    """Return ``drjit.llvm.ad``, or raise a clear error before anything can crash.

    Raises ``LLVMUnavailableError`` naming the fix when no libLLVM >= 19 is loaded (15 and 16 abort
    the process in the first min/max kernel, so this must be checked before compiling anything).
    """
    if _llvm.problem is not None:
        raise _llvm.LLVMUnavailableError(_llvm.problem)
    if not dr.has_backend(dr.JitBackend.LLVM):
        raise _llvm.LLVMUnavailableError(
            f"Dr.Jit's LLVM backend is inactive (no libLLVM loaded). {_llvm.INSTALL_HINT}"
        )
    major = dr.detail.llvm_version()[0]
    if major < _llvm.MIN_LLVM_MAJOR:
        raise _llvm.LLVMUnavailableError(
            f"Dr.Jit loaded libLLVM {major}, which crashes the process in min/max kernels "
            f"(drjit was probably imported before usplat_dr). {_llvm.INSTALL_HINT}"
        )
    import drjit.llvm.ad  # after the libLLVM checks above

    portable.pin_drjit()  # before the first kernel compiles (a no-op unless USPLAT_PORTABLE)
    return drjit.llvm.ad


def require_cuda() -> types.ModuleType:
    """Return ``drjit.cuda.ad``, or raise when Dr.Jit finds no CUDA device."""
    if not dr.has_backend(dr.JitBackend.CUDA):
        raise RuntimeError(
            "Dr.Jit's CUDA backend is unavailable (no NVIDIA GPU or driver found); "
            "use CPU tensors for the LLVM backend"
        )
    import drjit.cuda.ad  # only once a CUDA device is known to exist

    return drjit.cuda.ad


def module_for(name: str) -> types.ModuleType:
    """``drjit.llvm.ad`` for ``"llvm"``/``"cpu"``, ``drjit.cuda.ad`` for ``"cuda"``."""
    if name in ("llvm", "cpu"):
        return require_llvm()
    if name == "cuda":
        return require_cuda()
    raise ValueError(f"backend must be 'llvm' or 'cuda', got {name!r}")


def module_of(array) -> types.ModuleType:
    """The Dr.Jit AD namespace (``drjit.llvm.ad`` or ``drjit.cuda.ad``) of a Dr.Jit array."""
    backend = dr.backend_v(array)
    if backend == dr.JitBackend.LLVM:
        return require_llvm()
    if backend == dr.JitBackend.CUDA:
        return require_cuda()
    raise ValueError(f"expected a Dr.Jit LLVM or CUDA array, got {type(array).__name__}")


def available_backends() -> list[str]:
    """Backends that can run here, in preference order (``cuda`` first when present)."""
    names = []
    if dr.has_backend(dr.JitBackend.CUDA):
        names.append("cuda")
    try:
        require_llvm()
        names.append("llvm")
    except _llvm.LLVMUnavailableError:
        pass
    return names
