#!/usr/bin/env bash
# usplat-dr's entry point for a fresh Debian/Ubuntu machine with Python >= 3.10.
#
#   bash scripts/run.sh demo [ARGS]    the main job: synthetic data, train (a) and (c), evaluate,
#                                      report (outputs/demo/report.md; --quick: small budget)
#   bash scripts/run.sh test [ARGS]    run the test suite (pytest ARGS); as root it also installs
#                                      Debian's chromium for the viewer's browser test
#   bash scripts/run.sh lint [ARGS]    the linter, run by CI before the tests (ruff check . ARGS)
#   bash scripts/run.sh doctor         report versions, libLLVM, backends, GPU
#   bash scripts/run.sh bench [ARGS]   rasteriser benchmark (train/bench/rasterizer.py)
#   bash scripts/run.sh setup          only install
#   bash scripts/run.sh gpu-check [D]  on a CUDA machine: the CUDA tests, the rasteriser and
#                                      UniqueSplat benchmarks on the GPU, a report in
#                                      D (default outputs/gpu_check/; wheels it lacks: .whl/)
#   bash scripts/run.sh gpu-train OUT [SECONDS] [STEPS]  on a CUDA machine: (a) fine-tuned one
#                                      octave up (256x256) from sets packed in .gpudata256/
#                                      (train/studies/gpu_train.sh), scored against the
#                                      half-size model upsampled; results in OUT
#   bash scripts/run.sh gpu-prepare      here, for gpu-train: renders and packs .gpudata256/,
#                                      downloads the drjit wheel into .whl/
#                                      (train/studies/gpu_prepare.sh)
#
# Each command first installs what it needs, once: Debian's libllvm19 when no libLLVM >= 19 is
# present (Dr.Jit's CPU backend; 15 and 16 crash it), a virtual environment in .venv (or
# $USPLAT_VENV), and the package with its test extras through constraints.txt (torch==2.13.0).
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
VENV=${USPLAT_VENV:-$ROOT/.venv}
PYTHON=${PYTHON:-python3}

say() { printf '[usplat] %s\n' "$*" >&2; }

ensure_python() {
    if ! command -v "$PYTHON" >/dev/null; then
        say "no $PYTHON found: install Python >= 3.10 (Debian/Ubuntu: sudo apt-get install python3 python3-venv)"
        exit 1
    fi
    if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 10))'; then
        say "$("$PYTHON" --version) is too old: usplat-dr needs Python >= 3.10 (set PYTHON=python3.X)"
        exit 1
    fi
}

ensure_libllvm() {
    if "$PYTHON" "$ROOT/usplat_dr/_llvm.py" >/dev/null; then
        return
    fi
    local cmd="apt-get update && apt-get install -y libllvm19"
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        say "no libLLVM >= 19 found (Dr.Jit's CPU backend needs one): installing libllvm19"
        DEBIAN_FRONTEND=noninteractive bash -c "$cmd" >&2
        "$PYTHON" "$ROOT/usplat_dr/_llvm.py" >/dev/null && return
        say "libllvm19 installed but not found in the usual library folders"
        exit 1
    fi
    say "no libLLVM >= 19 found (Dr.Jit's CPU backend needs one; 15 and 16 crash it). Run:"
    say "    sudo sh -c '$cmd'"
    say "or point DRJIT_LIBLLVM_PATH at a libLLVM >= 19, then run this command again."
    exit 1
}

ensure_venv() {
    if [ ! -x "$VENV/bin/python" ]; then
        say "creating the virtual environment $VENV"
        if ! "$PYTHON" -m venv "$VENV"; then
            rm -rf "$VENV"
            say "could not create a virtual environment: install venv support"
            say "    (Debian/Ubuntu: sudo apt-get install python3-venv)"
            exit 1
        fi
    fi
    # Reinstall only when the requirements changed (hash of pyproject.toml + constraints.txt).
    local stamp
    stamp=$(cat "$ROOT/pyproject.toml" "$ROOT/constraints.txt" | sha256sum | cut -c1-16)
    if [ "$(cat "$VENV/.usplat-installed" 2>/dev/null)" != "$stamp" ]; then
        say "installing usplat-dr and its dependencies into $VENV (first run: a few minutes)"
        "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check \
            -c "$ROOT/constraints.txt" -e "$ROOT[test]" >&2
        # lpips (the tests' reference for our LPIPS) without its torchvision requirement: the
        # index's torchvision wheels are CUDA builds that do not load with the CPU torch.
        "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps \
            -c "$ROOT/constraints.txt" lpips >&2
        echo "$stamp" > "$VENV/.usplat-installed"
    fi
}

# usplat view's browser test (tests/jobs/test_view.py) drives headless Chromium; without one it
# skips. As root, `test` installs Debian's chromium (about 115 MB to download, 415 MB on disk).
ensure_chromium() {
    local name
    for name in chromium chromium-headless-shell chromium-browser google-chrome; do
        command -v "$name" >/dev/null && return
    done
    local cmd="apt-get update && apt-get install -y --no-install-recommends chromium"
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        say "no Chromium found (usplat view's browser test drives one): installing chromium"
        DEBIAN_FRONTEND=noninteractive bash -c "$cmd" >&2
        return
    fi
    say "no Chromium found: usplat view's browser test will skip (to run it: sudo sh -c '$cmd')"
}

setup() { ensure_python; ensure_libllvm; ensure_venv; }

# A GPU machine may have no network: it uses the Python that has a CUDA torch (none is
# installed), adds the wheels found in .whl/ (drjit's, jaxtyping's, ...: pip download them
# where there is a network) to a private site folder, and leaves everything else alone.
gpu_env() {
    # a private folder (mktemp -d: made anew, the user's own, mode 700): a fixed path in /tmp
    # would put whatever anyone planted there first on the import path
    local site=""
    if ls "$ROOT"/.whl/*.whl >/dev/null 2>&1; then
        site=$(mktemp -d "${TMPDIR:-/tmp}/usplat-gpu-site.XXXXXX")
        say "installing the wheels in .whl/ into $site"
        "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
            --upgrade --target "$site" "$ROOT"/.whl/*.whl >&2
    fi
    export PYTHONPATH="${site:+$site:}$ROOT${PYTHONPATH:+:$PYTHONPATH}"
    if ! "$PYTHON" -c 'import torch, sys; sys.exit(not torch.cuda.is_available())'; then
        say "torch sees no CUDA GPU here: $command needs a CUDA machine with torch installed"
        exit 1
    fi
    if ! "$PYTHON" -c 'import usplat_dr, drjit as dr, sys; sys.exit(not dr.has_backend(dr.JitBackend.CUDA))'; then
        say "Dr.Jit's CUDA backend is unavailable: put a drjit wheel for this Python in .whl/"
        exit 1
    fi
}

gpu_check() {
    local out=${1:-$ROOT/outputs/gpu_check}
    mkdir -p "$out"
    gpu_env
    {
        echo "# usplat-dr GPU check, $(date -u +%Y-%m-%dT%H:%MZ)"
        echo
        echo '```'
        nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || true
        "$PYTHON" -c 'import sys, torch, drjit; print("python", sys.version.split()[0], "torch", torch.__version__, "cuda", torch.version.cuda, "drjit", drjit.__version__)'
        echo '```'
        echo
        echo "## CUDA tests (the CUDA variants of every test parametrised over the devices)"
        echo
        echo '```'
        # "not llvm": a GPU image may have no libLLVM >= 19 for the CPU variants.
        "$PYTHON" -m pytest -q -p no:cacheprovider -k "cuda and not llvm" -rs tests 2>&1 \
            | grep -v "jit_find_library\|jitc_llvm_init" | tail -n 40 || true
        echo '```'
        echo
        echo "## Rasteriser on the GPU (train/bench/rasterizer.py --device cuda)"
        echo
        "$PYTHON" train/bench/rasterizer.py --device cuda --sizes 64 256 --dense-max 64 2>&1 \
            | grep -v "jit_find_library\|jitc_llvm_init" || true
        echo
        echo "## UniqueSplat (c)/(a) on the GPU (train/bench/uniquesplat.py --device cuda)"
        echo
        echo '```'
        "$PYTHON" train/bench/uniquesplat.py --device cuda --processes 1 --repeats 10 --layers \
            2>&1 | grep -v "jit_find_library\|jitc_llvm_init" || true
        echo '```'
    } | tee "$out/report.md"
    say "report: $out/report.md"
}

command=${1:-}
[ $# -gt 0 ] && shift
case "$command" in
    setup) setup ;;
    demo) setup; cd "$ROOT"; exec "$VENV/bin/usplat" demo "$@" ;;
    test) setup; ensure_chromium; cd "$ROOT"; exec "$VENV/bin/python" -m pytest "$@" ;;
    lint) setup; cd "$ROOT"; exec "$VENV/bin/ruff" check . "$@" ;;
    doctor) setup; exec "$VENV/bin/usplat" doctor ;;
    bench) setup; cd "$ROOT"; exec "$VENV/bin/python" train/bench/rasterizer.py "$@" ;;
    gpu-check) cd "$ROOT"; gpu_check "$@" ;;
    gpu-train) cd "$ROOT"; gpu_env; exec bash train/studies/gpu_train.sh "$@" ;;
    gpu-prepare) setup; cd "$ROOT"; PYTHON="$VENV/bin/python" exec bash train/studies/gpu_prepare.sh ;;
    *) sed -n '2,25p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//' >&2; exit 2 ;;
esac
