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


@pytest.mark.parametrize("argv, message", [
    (["render-demo", "--size", "0"], "--size: must be an integer >= 1, got '0'"),
    (["synth", "--out", "x", "--frames", "2"], "--frames: must be an integer >= 3"),
    (["fit", "--iterations", "zero"], "--iterations: must be an integer >= 1, got 'zero'"),
    (["bench", "--prunes", "all,nope"], "--prunes: unknown ['nope']"),
    (["bench", "--configs", "tiny:z"], "--configs: 'tiny:z' is not preset:variant"),
    (["eval", "--checkpoint", "c", "--data", "d", "--device", "tpu"], "invalid choice: 'tpu'"),
    (["no-such-command"], "invalid choice: 'no-such-command'"),
])
def test_cli_rejects_bad_arguments_as_usage_errors(argv, message, capsys):
    # argparse checks types and choices: exit status 2 and the message, before any work
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_train_names_a_bad_config_value_and_where_it_was_set():
    with pytest.raises(SystemExit, match=r"usplat train: train\.steps='abc': expected int.*"
                                         r"command line \(train\.steps=abc\)"):
        main(["train", "--config", "synthetic_tiny.yaml", "train.steps=abc"])


def test_cli_commands_are_a_table_of_job_modules():
    from usplat_dr.cli import COMMANDS

    for name in ("demo", "bench", "train", "eval", "render", "export-ply", "render-demo",
                 "fit", "synth", "params", "doctor"):
        assert name in COMMANDS
    with pytest.raises(SystemExit) as exit_info:  # each command's own arguments
        main(["train", "--help"])
    assert exit_info.value.code == 0


@pytest.mark.parametrize("module", [
    "usplat_dr.render.bridge", "usplat_dr.render.pipeline", "usplat_dr._llvm",
    "usplat_dr.geometry.cameras", "usplat_dr.geometry.quaternions", "usplat_dr.io.atomic",
    "usplat_dr.evaluation.metrics", "usplat_dr.data.chunks", "usplat_dr.data.shims",
    "usplat_dr.data.view_sampler", "usplat_dr.data.dataset", "usplat_dr.data.synth",
    "usplat_dr.data.synth.textures", "usplat_dr.data.synth.scenes",
    "usplat_dr.model.encoder.primary", "usplat_dr.model.sh_rotation",
    "usplat_dr.model.hypernet.resnet", "usplat_dr.jobs.report", "usplat_dr.jobs.arguments",
    "usplat_dr.data.types", "usplat_dr.config", "usplat_dr.training.distributed"])
def test_docstring_examples_run(module):
    result = doctest.testmod(importlib.import_module(module))
    assert result.attempted > 0 and result.failed == 0
