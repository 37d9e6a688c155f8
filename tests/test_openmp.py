"""``usplat_dr._openmp``: GOMP_SPINCOUNT is set before torch loads, and never over a user's
choice."""

import os
import subprocess
import sys

import pytest

from usplat_dr import _openmp


@pytest.fixture
def clean(monkeypatch):
    for var in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY", _openmp.ENV_VAR):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.delitem(sys.modules, "torch", raising=False)  # as if torch were not loaded
    monkeypatch.setattr(_openmp, "outcome", _openmp.outcome)  # restored after the test
    return monkeypatch


def test_sets_the_default_spin_count(clean):
    assert _openmp.configure() == _openmp.DEFAULT_SPIN
    assert os.environ["GOMP_SPINCOUNT"] == _openmp.DEFAULT_SPIN
    assert _openmp.describe() == ("GOMP_SPINCOUNT=30000, OMP_WAIT_POLICY unset: set by "
                                  "usplat_dr (USPLAT_OMP_SPIN, default 30000)")


def test_users_choice_wins(clean):
    clean.setenv(_openmp.ENV_VAR, "1234")
    assert _openmp.configure() == "1234"
    clean.setenv("GOMP_SPINCOUNT", "7")
    assert _openmp.configure() is None and os.environ["GOMP_SPINCOUNT"] == "7"
    clean.delenv("GOMP_SPINCOUNT")
    clean.setenv("OMP_WAIT_POLICY", "PASSIVE")
    assert _openmp.configure() is None and "GOMP_SPINCOUNT" not in os.environ
    assert _openmp.describe() == ("GOMP_SPINCOUNT unset, OMP_WAIT_POLICY=PASSIVE: set outside "
                                  "usplat_dr (it wins)")


def test_off_and_too_late_leave_libgomp_alone(clean):
    clean.setenv(_openmp.ENV_VAR, "off")
    assert _openmp.configure() is None and "GOMP_SPINCOUNT" not in os.environ
    clean.delenv(_openmp.ENV_VAR)
    clean.setitem(sys.modules, "torch", object())  # torch (and libgomp) already loaded
    assert _openmp.configure() is None and "GOMP_SPINCOUNT" not in os.environ
    assert "torch was imported before it" in _openmp.describe()


def test_bad_value_names_the_variable(clean):
    clean.setenv(_openmp.ENV_VAR, "fast")
    with pytest.raises(ValueError, match="USPLAT_OMP_SPIN must be"):
        _openmp.configure()


def test_import_sets_it_before_torch():
    env = {k: v for k, v in os.environ.items()
           if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY", _openmp.ENV_VAR)}
    code = "import usplat_dr, os, sys; print(os.environ['GOMP_SPINCOUNT'], 'torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == [_openmp.DEFAULT_SPIN, "False"]
