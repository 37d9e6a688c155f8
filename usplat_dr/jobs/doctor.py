"""``usplat doctor``: what this machine has for usplat-dr, and what to fix."""

import argparse
import importlib
import os
import platform
import sys

from usplat_dr import _llvm, _threads, portable


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
        print(f"  CPU code path: {torch.backends.cpu.get_cpu_capability()}")
        cuda = torch.cuda.is_available()
        print(f"  CUDA: {torch.cuda.get_device_name(0) if cuda else 'no GPU'}")
        if cuda and "cuda" not in backends:
            problems.append("torch sees a GPU but Dr.Jit's CUDA backend is unavailable "
                            "(driver too old?): CUDA tensors cannot be rendered")
    except Exception as e:  # noqa: BLE001
        print(f"  unavailable ({e})")

    problems += _numerics("llvm" in backends)
    _core_keeper()

    if problems:
        print("\nProblems:")
        for p in problems:
            print(f"  - {p}")
        return 1
    print("\nAll good.")
    return 0


def _numerics(llvm: bool) -> list[str]:
    """Portable numerics (``usplat_dr.portable``) and the OpenMP spin (``usplat_dr._threads``),
    as this process has them (``usplat`` turns portable numerics on before torch loads), and
    the thread count ``usplat``'s commands would start with (``usplat_dr._threads``); returns
    problems to report."""
    pins = portable.describe()
    print("\nNumerics and threads")
    print(f"  portable numerics: {'on' if pins['portable'] else 'off'} ({portable.ENV_VAR}="
          f"{os.environ.get(portable.ENV_VAR, '(unset)')})")
    print("  torch pins: " + ", ".join(f"{k}={pins[k] or '(unset)'}" for k in portable.TORCH_ENV))
    target = portable.drjit_target() if llvm else None
    if target is None:
        print("  Dr.Jit LLVM target: unknown")
    else:
        pinned = "pinned" if pins["drjit_target"] else "not pinned: the host CPU's"
        print(f"  Dr.Jit LLVM target: {target[0]}, {target[2]} float lanes ({pinned})")
    print(f"  OpenMP spin: {_threads.describe()}")
    problems = []
    if _threads.outcome.startswith("not set: "):  # a value usplat_dr could not use
        problems.append(f"OpenMP spin {_threads.outcome}")
    try:
        choice = _threads.choose()
        print(f"  usplat's commands start with {choice.line()}")
    except ValueError as e:
        print(f"  threads: {e}")
        problems.append(str(e))
    return problems


def _core_keeper() -> None:
    """The wake-up probe and what ``keep_cores_awake: auto`` decides here for a CPU run on
    every core (``usplat_dr.training.cores``)."""
    print("\nCore keeper (keep_cores_awake)")
    try:  # the training package imports torch and the model: may be broken (reported above)
        from usplat_dr.training import cores as _cores
    except Exception as e:  # noqa: BLE001
        print(f"  unavailable ({e})")
        return
    cpus = len(_cores.available_cpus())
    probe = _cores.probe_wake_latency()
    on, why = _cores.decide("auto", cpus, "cpu", measure=lambda: probe)
    hyper = {True: "yes", False: "no", None: "unknown"}[_cores.hypervisor()]
    if probe is None:
        print("  idle-core wake-up: the probe could not run here")
    else:
        print(f"  idle-core wake-up: {probe.median_us:.0f} us median of {probe.rounds} (10-90 %: "
              f"{probe.low_us:.0f}-{probe.high_us:.0f} us), threshold "
              f"{_cores.WAKE_THRESHOLD_US:.0f} us")
    print(f"  hypervisor flag: {hyper}, cpuidle driver: {_cores.cpuidle_driver() or 'unknown'}")
    print(f"  auto, a CPU run on {cpus} core(s): {_cores.log_line(on, why)}")


if __name__ == "__main__":
    sys.exit(run())
