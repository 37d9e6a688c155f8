"""The ``usplat`` command line and the doctests of the public API."""

import doctest
import importlib
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from usplat_dr.cli import main


def test_doctor_reports_and_succeeds_here():
    r = subprocess.run([sys.executable, "-m", "usplat_dr", "doctor"], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    for needle in ("drjit", "mitsuba", "torch", "numpy", "libLLVM 19", "backends: ",
                   "threads", "LLVM min/max kernel: ok", "llvm_ad_rgb", "CUDA"):
        assert needle in r.stdout, needle


def test_doctor_exits_nonzero_with_advice_without_llvm(tmp_path):
    import os

    env = dict(os.environ, DRJIT_LIBLLVM_PATH=str(tmp_path / "libLLVM-15.so.1"))
    (tmp_path / "libLLVM-15.so.1").write_bytes(b"")
    r = subprocess.run([sys.executable, "-m", "usplat_dr", "doctor"], capture_output=True,
                       text=True, timeout=300, env=env)
    assert r.returncode == 1
    assert "libllvm19" in r.stdout and "Problems" in r.stdout


def test_render_demo_writes_images(tmp_path):
    assert main(["-q", "render-demo", "--out", str(tmp_path), "--size", "48", "--views",
                 "2"]) == 0
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["contact_sheet.png"] + [f"view{v:02d}_{k}.png" for v in range(2)
                                             for k in ("alpha", "color", "depth")]
    color = np.asarray(Image.open(tmp_path / "view00_color.png"))
    assert color.shape == (48, 48, 3)
    assert color.std() > 10  # a scene, not a blank image
    alpha = np.asarray(Image.open(tmp_path / "view00_alpha.png"))
    assert 0 < (alpha > 128).mean() < 1  # foreground and sky


def test_cli_rejects_bad_arguments():
    with pytest.raises(SystemExit):
        main(["render-demo", "--size", "0"])
    with pytest.raises(SystemExit):
        main(["no-such-command"])


@pytest.mark.parametrize("module", [
    "usplat_dr.render.bridge", "usplat_dr.render.pipeline", "usplat_dr._llvm",
    "usplat_dr.geometry.cameras", "usplat_dr.geometry.quaternions", "usplat_dr.io.atomic",
    "usplat_dr.evaluation.metrics", "usplat_dr.data.chunks", "usplat_dr.data.shims",
    "usplat_dr.data.view_sampler", "usplat_dr.data.dataset", "usplat_dr.data.synth",
    "usplat_dr.data.synth.textures", "usplat_dr.data.synth.scenes",
    "usplat_dr.model.encoder.primary", "usplat_dr.model.sh_rotation",
    "usplat_dr.model.hypernet.resnet", "usplat_dr.jobs.report", "usplat_dr.jobs.arguments",
    "usplat_dr.data.types"])
def test_docstring_examples_run(module):
    result = doctest.testmod(importlib.import_module(module))
    assert result.attempted > 0 and result.failed == 0
