"""Choose the libLLVM that Dr.Jit's LLVM backend loads, before drjit is imported.

Dr.Jit 1.5 reads ``DRJIT_LIBLLVM_PATH`` once, when ``drjit`` is first imported (also through
``import mitsuba``). Without it, Dr.Jit globs the multiarch library directory and takes the
natural-sort last file, so which libLLVM wins depends on which packages happen to be installed.
That matters: libLLVM 14 is refused, and 15 and 16 abort the whole process (SIGABRT, "LLVM ERROR:
Cannot select ... fminimum") in any kernel with a min/max. 19 and 22 are known to work
(``docs/rasteriser_notes.md``, "libLLVM"). This module has no third-party imports.
"""

import glob
import os
import re
import sys

#: Oldest libLLVM major version we let Dr.Jit load (15 and 16 crash; 17 and 18 are untested).
MIN_LLVM_MAJOR = 19

ENV_VAR = "DRJIT_LIBLLVM_PATH"
_NO_LLVM = "/nonexistent/usplat-dr-found-no-libLLVM-19-or-newer.so"

_SEARCH_GLOBS = (
    "/usr/lib/*-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/lib/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/usr/local/opt/llvm/lib/libLLVM*.dylib",
    "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib",
)

# Debian/Ubuntu name it libLLVM-15.so.1, libLLVM-19.so, libLLVM.so.19.1; llvm.org builds
# /usr/lib/llvm-19/lib/libLLVM.so.19.1 or libLLVM-19.so; Homebrew libLLVM.dylib.
_VERSION_PATTERNS = (
    re.compile(r"libLLVM-(\d+)(?:\.\d+)*\.(?:so|dylib)"),
    re.compile(r"libLLVM\.so\.(\d+)"),
    re.compile(r"libLLVM-(\d+)"),
    re.compile(r"llvm-(\d+)/lib/"),
    re.compile(r"llvm@(\d+)/"),
)

INSTALL_HINT = (
    f"Install a libLLVM >= {MIN_LLVM_MAJOR} (Debian 12 / Ubuntu 24.04: "
    "`sudo apt-get install libllvm19`) or "
    "point DRJIT_LIBLLVM_PATH at one (e.g. export DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/"
    "libLLVM-19.so) before importing usplat_dr."
)


def llvm_major_from_path(path: str) -> int | None:
    """Major version encoded in a libLLVM file name, or ``None`` when it carries none.

    Examples:
        >>> llvm_major_from_path("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1")
        15
        >>> llvm_major_from_path("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1")
        19
        >>> llvm_major_from_path("/usr/lib/llvm-22/lib/libLLVM.so") is None
        False
    """
    for pattern in _VERSION_PATTERNS:
        match = pattern.search(path)
        if match:
            return int(match.group(1))
    return None


def find_libllvm(globs: tuple[str, ...] = _SEARCH_GLOBS) -> list[tuple[int, str]]:
    """All libLLVM files with a known major version in the usual locations, newest first."""
    found: dict[str, tuple[int, str]] = {}
    for pattern in globs:
        for path in glob.glob(pattern):
            major = llvm_major_from_path(path)
            if major is None or not os.path.isfile(path):
                continue
            real = os.path.realpath(path)
            # Several names (symlinks) point at one library: keep one entry per file.
            found.setdefault(real, (major, path))
    return sorted(found.values(), key=lambda mp: (-mp[0], mp[1]))


def choose_libllvm(globs: tuple[str, ...] = _SEARCH_GLOBS) -> str | None:
    """Path of the newest libLLVM with major >= ``MIN_LLVM_MAJOR``, or ``None``."""
    for major, path in find_libllvm(globs):
        if major >= MIN_LLVM_MAJOR:
            return path
    return None


#: Why the LLVM backend cannot be used, or ``None``. Set by :func:`configure`.
problem: str | None = None


def configure() -> None:
    """Set ``DRJIT_LIBLLVM_PATH`` when unset; record a problem instead of crashing later.

    Called from ``usplat_dr/__init__.py``. It does not raise, so the CUDA backend and
    ``usplat doctor`` keep working on machines without a usable libLLVM; using the LLVM backend
    then raises :class:`LLVMUnavailableError` (see :func:`usplat_dr.backend.require_llvm`).
    """
    global problem
    problem = None
    user_path = os.environ.get(ENV_VAR)
    if user_path == _NO_LLVM:
        user_path = None
    if user_path:
        major = llvm_major_from_path(user_path)
        if not os.path.isfile(user_path):
            problem = f"{ENV_VAR}={user_path} does not exist. {INSTALL_HINT}"
        elif major is not None and major < MIN_LLVM_MAJOR:
            problem = (
                f"{ENV_VAR}={user_path} is libLLVM {major}; Dr.Jit 1.5 refuses 14 and crashes "
                f"the process with 15 and 16. {INSTALL_HINT}"
            )
        return
    if "drjit" in sys.modules:
        # Too late to choose: Dr.Jit already picked one; backend.require_llvm() checks it.
        return
    path = choose_libllvm()
    if path is None:
        found = ", ".join(f"{p} ({m})" for m, p in find_libllvm()) or "none"
        problem = f"No libLLVM >= {MIN_LLVM_MAJOR} found (found: {found}). {INSTALL_HINT}"
        # Left unset, Dr.Jit would glob for any libLLVM and might load 15 or 16, which abort the
        # process in the first min/max kernel. A path that does not exist leaves the LLVM backend
        # inactive instead (a Python ImportError), and the CUDA backend unaffected.
        os.environ[ENV_VAR] = _NO_LLVM
        return
    os.environ[ENV_VAR] = path


class LLVMUnavailableError(RuntimeError):
    """The Dr.Jit LLVM (CPU) backend cannot be used safely on this machine."""


if __name__ == "__main__":
    # Used by scripts/run.sh before any package is installed: print the chosen libLLVM, or exit 1.
    chosen = choose_libllvm()
    if chosen is None:
        sys.exit(1)
    print(chosen)
