"""Shorten how long torch's OpenMP worker threads spin after each parallel operation, before
torch is imported.

torch's CPU wheels use GNU OpenMP. After a parallel operation its workers keep spinning on
their cores (libgomp's default: 300,000 iterations, milliseconds) before they sleep. The
rasteriser runs on Dr.Jit's own thread pool, so right after a torch operation its threads
shared the two cores with spinning torch workers: at 2 threads a 64x64 forward+backward took
10.4 ms instead of 4.9, and the torch bridge added 6-13 ms over the Dr.Jit entry instead of
about 1 (train/bench/README.md, "OpenMP spinning"; ``train/bench/omp_spin.py``). A spin count of
30,000 kept torch's own operations as fast (training steps 0.93-0.99x), where
``OMP_WAIT_POLICY=PASSIVE`` (no spinning) made a training step 1.7x slower.

libgomp reads ``GOMP_SPINCOUNT`` once, when it loads (with torch), so this runs on
``import usplat_dr``, which must come before ``import torch`` for it to apply. A value the
user set for ``GOMP_SPINCOUNT`` or ``OMP_WAIT_POLICY`` wins; ``USPLAT_OMP_SPIN`` chooses ours
(a number, or ``off`` for libgomp's default). This module has no third-party imports.
"""

import os
import sys

ENV_VAR = "USPLAT_OMP_SPIN"
DEFAULT_SPIN = "30000"

#: What the last ``configure`` did, in words (``describe``; ``usplat doctor``).
outcome = "not configured (usplat_dr was not imported?)"


def configure() -> str | None:
    """Set ``GOMP_SPINCOUNT`` when nothing else decides it; return the value set (or None)."""
    global outcome
    choice = os.environ.get(ENV_VAR, DEFAULT_SPIN).strip().lower()
    if choice == "off":
        outcome = f"libgomp's default ({ENV_VAR}=off)"
        return None
    if "torch" in sys.modules:  # too late: torch (and libgomp) already loaded
        outcome = "not set by usplat_dr: torch was imported before it"
        return None
    if "GOMP_SPINCOUNT" in os.environ or "OMP_WAIT_POLICY" in os.environ:
        outcome = "set outside usplat_dr (it wins)"
        return None
    if not choice.isdigit():
        raise ValueError(f"{ENV_VAR} must be a non-negative integer or 'off', got "
                         f"{os.environ[ENV_VAR]!r}")
    os.environ["GOMP_SPINCOUNT"] = choice
    outcome = f"set by usplat_dr ({ENV_VAR}, default {DEFAULT_SPIN})"
    return choice


def describe() -> str:
    """The OpenMP spin setting now and who chose it, e.g. ``GOMP_SPINCOUNT=30000,
    OMP_WAIT_POLICY unset: set by usplat_dr (USPLAT_OMP_SPIN, default 30000)``."""
    values = ", ".join(f"{k}={os.environ[k]}" if k in os.environ else f"{k} unset"
                       for k in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY"))
    return f"{values}: {outcome}"
