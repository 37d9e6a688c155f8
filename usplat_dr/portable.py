"""Portable numerics: the same float results from the same command on any x86-64 CPU with
AVX2 and FMA, whatever else the CPU has (docs/reproducibility.md).

Machines of one kind are not one CPU: ours are AMD Zen 3 (AVX2, 8 float lanes) and Intel
Cascade Lake (AVX-512, 16 lanes). Each library picks code for the CPU it finds: Dr.Jit's LLVM
backend (the rasteriser, and Mitsuba rendering the synthetic data) compiles for the host with
its widest vectors, torch dispatches to AVX2 or AVX-512 kernels, oneDNN and MKL likewise. Other
instructions and vector widths round differently, and training amplifies the last bits into
different models. With ``USPLAT_PORTABLE=1`` (the ``usplat`` command's default; ``0`` turns
it off) every library is held to the AVX2 code path:

- Dr.Jit: LLVM target ``haswell`` (AVX2 + FMA), 8 lanes (``jit_llvm_set_target``, a C
  function of drjit-core that Dr.Jit's Python API does not expose, called through ctypes);
- torch: ``ATEN_CPU_CAPABILITY=avx2``, oneDNN ``ONEDNN_MAX_CPU_ISA=AVX2``, MKL
  ``MKL_CBWR=AVX2`` (set before torch is imported; a value the user set wins).

What this cannot pin: oneDNN and MKL choose blocking from cache sizes, and more threads
reorder float sums; training with ``threads=1`` removes the latter.

This module has no third-party imports (``usplat_dr/__init__`` may import it).
"""

import ctypes
import functools
import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)

ENV_VAR = "USPLAT_PORTABLE"
TORCH_ENV = {"ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2", "MKL_CBWR": "AVX2"}
#: Dr.Jit's LLVM target: CPU, features, float lanes per packet.
DRJIT_TARGET = ("haswell", "+avx,+avx2,+fma,+f16c,+popcnt,+sse4.2,+bmi,+bmi2,+lzcnt", 8)

_pinned: tuple | None = None
_host: tuple | None = None  # Dr.Jit's target before the first pin (``unpin_drjit``)


#: ``USPLAT_PORTABLE``'s values: off, and on.
OFF, ON = ("", "0", "false", "no", "off"), ("1", "true", "yes", "on")
_said: set[str] = set()  # values already warned about


def enabled() -> bool:
    """Whether portable numerics are on (``USPLAT_PORTABLE``); a value that is neither
    (``OFF``, ``ON``) is said once, naming the variable and its values, and counts as on
    (the numbers stay reproducible)."""
    value = os.environ.get(ENV_VAR, "0").strip().lower()
    if value not in OFF + ON and value not in _said:
        _said.add(value)
        logging.getLogger(__name__).warning(
            "%s=%r is not one of 1/true/yes/on or 0/false/no/off: treated as 1 (portable "
            "numerics on)", ENV_VAR, os.environ.get(ENV_VAR))
    return value not in OFF


def enable(torch_pins: bool = True) -> None:
    """Turn portable numerics on for this process (``usplat``'s commands do): sets the
    environment torch reads. Call before torch is imported to take effect there.
    ``torch_pins=False`` leaves torch, oneDNN and MKL free (Dr.Jit stays pinned): for bfloat16
    inference, whose kernels differ between CPUs anyway and which oneDNN's AVX2 code runs
    about 14x slower than float32 (train/bench/README.md, "bfloat16 inference")."""
    os.environ.setdefault(ENV_VAR, "1")
    if enabled() and torch_pins:
        for key, value in TORCH_ENV.items():
            os.environ.setdefault(key, value)


@functools.cache
def _host_has_avx2_fma() -> bool:
    try:
        flags = next((line for line in Path("/proc/cpuinfo").read_text().splitlines()
                      if line.startswith("flags")), "").split()
    except OSError:
        return False
    return {"avx2", "fma", "f16c"} <= set(flags)


def _core():
    import drjit as dr  # not at import: usplat_dr/__init__ imports this before libLLVM is set

    return ctypes.CDLL(str(Path(dr.__file__).parent / "libdrjit-core.so"))


def drjit_target() -> tuple[str, str, int] | None:
    """Dr.Jit's LLVM target now (CPU, features, lanes), or None where it cannot be read."""
    try:
        lib = _core()
        cpu, feat = lib._Z19jit_llvm_target_cpuv, lib._Z24jit_llvm_target_featuresv
        width = lib._Z21jit_llvm_vector_widthv
    except (OSError, AttributeError):
        return None
    cpu.restype = feat.restype = ctypes.c_char_p
    width.restype = ctypes.c_uint32
    return (cpu() or b"").decode(), (feat() or b"").decode(), int(width())


def pin_drjit(target: tuple[str, str, int] = DRJIT_TARGET) -> bool:
    """Point Dr.Jit's LLVM backend at ``target`` (kernels compiled from then on; the target
    is part of each kernel's code, so cached kernels of another target are not reused).
    Does nothing unless portable numerics are on and the host has AVX2 and FMA. Returns
    whether the target is pinned."""
    global _pinned
    if _pinned == target:  # the common case: called before every CPU render
        return True
    if not enabled() or not _host_has_avx2_fma():
        return False
    try:
        lib = _core()
        set_target = lib._Z19jit_llvm_set_targetPKcS0_j
    except (OSError, AttributeError):
        log.warning("%s: this Dr.Jit build has no jit_llvm_set_target; kernels follow the "
                    "host CPU", ENV_VAR)
        return False
    set_target.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
    set_target.restype = None
    global _host
    if _host is None:
        _host = drjit_target()
    set_target(target[0].encode(), target[1].encode(), target[2])
    _pinned = target
    return True


def unpin_drjit() -> None:
    """Undo ``pin_drjit``: Dr.Jit compiles for the host CPU again (kernels compiled from then
    on). For a process that turns portable numerics off after a pinned ``usplat`` call in
    it (the test suite between tests)."""
    global _pinned
    if _pinned is None or not _host:
        return
    set_target = _core()._Z19jit_llvm_set_targetPKcS0_j
    set_target.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
    set_target.restype = None
    set_target(_host[0].encode(), _host[1].encode(), _host[2])
    _pinned = None


def describe() -> dict:
    """What is pinned, for provenance records."""
    return {"portable": enabled(), "drjit_target": drjit_target() if _pinned else None,
            **{k: os.environ.get(k) for k in TORCH_ENV}}
