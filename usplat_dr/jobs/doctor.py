"""``usplat doctor``: what this machine has for usplat-dr, and what to fix."""

import argparse
import importlib
import os
import platform
import sys

from usplat_dr import _llvm


def _version(module: str) -> str | None:
    try:
        return importlib.import_module(module).__version__
    except Exception:  # noqa: BLE001  (any import failure means "not usable")
        return None


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``usplat doctor`` takes no arguments."""


def run(args: argparse.Namespace | None = None) -> int:
    """Print the report; return 0 when everything needed for CPU rendering works, else 1."""
    problems: list[str] = []
    print(f"usplat-dr doctor  (Python {platform.python_version()}, {platform.platform()})")

    print("\nPackages")
    for name in ("drjit", "mitsuba", "torch", "numpy"):
        version = _version(name)
        print(f"  {name:<8} {version or 'MISSING'}")
        if version is None:
            problems.append(f"{name} is not installed: run `bash scripts/run.sh setup` "
                            f"(or `pip install -c constraints.txt -e .`)")

    print("\nlibLLVM (Dr.Jit's CPU backend)")
    print(f"  {_llvm.ENV_VAR} = {os.environ.get(_llvm.ENV_VAR, '(unset)')}")
    candidates = _llvm.find_libllvm()
    print("  found: " + (", ".join(f"{p} ({m})" for m, p in candidates) or "none"))
    if _llvm.problem:
        problems.append(_llvm.problem)

    # after the libLLVM report above, so that it prints even if loading Dr.Jit fails
    import drjit as dr

    from usplat_dr.backend import available_backends, require_llvm  # loads drjit (above)

    backends = available_backends()
    if dr.has_backend(dr.JitBackend.LLVM):
        print(f"  loaded: libLLVM {'.'.join(map(str, dr.detail.llvm_version()))}")
    print("\nDr.Jit")
    print(f"  backends: {', '.join(backends) or 'none'}")
    print(f"  threads:  {dr.thread_count()} (CPU cores: {os.cpu_count()})")
    if "llvm" in backends:
        # A min/max kernel: what crashes the process with libLLVM 15/16 (refused above).
        llvm = require_llvm()
        ok = dr.allclose(dr.minimum(llvm.Float(1, 5), llvm.Float(3, 2)), llvm.Float(1, 2))
        print(f"  LLVM min/max kernel: {'ok' if ok else 'WRONG RESULT'}")
        if not ok:
            problems.append("Dr.Jit's LLVM backend computed a wrong min/max")
    else:
        problems.append("Dr.Jit's LLVM (CPU) backend is unusable; " + _llvm.INSTALL_HINT)

    print("\nMitsuba")
    try:
        import mitsuba as mi  # may be missing or broken: reported, not raised

        print(f"  variants: {', '.join(mi.variants())}")
    except Exception as e:  # noqa: BLE001
        print(f"  unavailable ({e})")
        problems.append("mitsuba is unavailable (needed for synthetic scenes, not for rendering"
                        " Gaussians)")

    print("\ntorch")
    try:
        import torch  # may be missing or broken: reported, not raised

        print(f"  threads: {torch.get_num_threads()}")
        # usplat_dr/_openmp.py: set on import, before torch loads
        print(f"  GOMP_SPINCOUNT = {os.environ.get('GOMP_SPINCOUNT', '(unset)')}, "
              f"OMP_WAIT_POLICY = {os.environ.get('OMP_WAIT_POLICY', '(unset)')}")
        cuda = torch.cuda.is_available()
        print(f"  CUDA: {torch.cuda.get_device_name(0) if cuda else 'no GPU'}")
        if cuda and "cuda" not in backends:
            problems.append("torch sees a GPU but Dr.Jit's CUDA backend is unavailable "
                            "(driver too old?): CUDA tensors cannot be rendered")
    except Exception as e:  # noqa: BLE001
        print(f"  unavailable ({e})")

    if problems:
        print("\nProblems:")
        for p in problems:
            print(f"  - {p}")
        return 1
    print("\nAll good.")
    return 0


if __name__ == "__main__":
    sys.exit(run())
