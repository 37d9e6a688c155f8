"""libLLVM selection (usplat_dr/_llvm.py) and the backend guard."""

import os
import subprocess
import sys

import pytest

from usplat_dr import _llvm


@pytest.mark.parametrize("path,major", [
    ("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1", 15),
    ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so", 19),
    ("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1", 19),
    ("/usr/lib/x86_64-linux-gnu/libLLVM-14.0.6.so.1", 14),
    ("/usr/lib/llvm-22/lib/libLLVM.so.22.1", 22),
    ("/usr/lib/llvm-18/lib/libLLVM.so", 18),
    ("/opt/homebrew/opt/llvm@19/lib/libLLVM.dylib", 19),
    ("/usr/lib/libLLVM.so", None),
])
def test_llvm_major_from_path(path, major):
    assert _llvm.llvm_major_from_path(path) == major


def _fake_libs(tmp_path, names):
    for name in names:
        (tmp_path / name).write_bytes(b"")
    return (str(tmp_path / "libLLVM*.so*"),)


def test_choose_prefers_the_newest_suitable(tmp_path):
    globs = _fake_libs(tmp_path, ["libLLVM-15.so.1", "libLLVM.so.19.1", "libLLVM.so.22.1",
                                  "libLLVM-14.so.1"])
    assert _llvm.choose_libllvm(globs).endswith("libLLVM.so.22.1")


def test_choose_refuses_crashing_versions(tmp_path):
    globs = _fake_libs(tmp_path, ["libLLVM-15.so.1", "libLLVM-16.so.1", "libLLVM-14.so.1"])
    assert _llvm.choose_libllvm(globs) is None
    assert [m for m, _ in _llvm.find_libllvm(globs)] == [16, 15, 14]


def _run(code, env):
    full = {k: v for k, v in os.environ.items() if k != _llvm.ENV_VAR}
    full.update(env)
    return subprocess.run([sys.executable, "-c", code], env=full, capture_output=True,
                          text=True, timeout=120, check=False)


def test_import_sets_the_variable_before_drjit():
    r = _run("import usplat_dr, os, drjit as dr; print(os.environ['DRJIT_LIBLLVM_PATH']);"
             "print(dr.detail.llvm_version()[0])", {})
    assert r.returncode == 0, r.stderr
    path, major = r.stdout.split()
    assert _llvm.llvm_major_from_path(path) >= _llvm.MIN_LLVM_MAJOR
    assert int(major) >= _llvm.MIN_LLVM_MAJOR


def test_a_crashing_libllvm_is_refused_with_advice_not_a_crash(tmp_path):
    # Points Dr.Jit at a libLLVM 15 by name; usplat_dr must raise before any kernel runs (the
    # file need not be a real library: Dr.Jit never gets to load it).
    fake = tmp_path / "libLLVM-15.so.1"
    fake.write_bytes(b"")
    r = _run("import usplat_dr\nfrom usplat_dr.backend import require_llvm\n"
             "try:\n    require_llvm()\nexcept Exception as e:\n    print(type(e).__name__, e)",
             {_llvm.ENV_VAR: str(fake)})
    assert r.returncode == 0, r.stderr
    assert "LLVMUnavailableError" in r.stdout and "libllvm19" in r.stdout


def test_rasterize_on_cpu_refuses_without_llvm(tmp_path):
    missing = tmp_path / "libLLVM-19.so"  # does not exist
    r = _run("import usplat_dr, torch\nfrom usplat_dr.render import rasterize\n"
             "from usplat_dr.render.scenes import random_scene\n"
             "try:\n    rasterize(*random_scene(4, 8, 8).args())\n"
             "except Exception as e:\n    print(type(e).__name__, e)",
             {_llvm.ENV_VAR: str(missing)})
    assert r.returncode == 0, r.stderr
    assert "LLVMUnavailableError" in r.stdout and "does not exist" in r.stdout
