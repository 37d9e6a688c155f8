"""The ``usplat`` command line and the doctests of the public API."""

import doctest
import importlib
import logging
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import plyfile
import pytest
from PIL import Image

import usplat_dr
from usplat_dr.cli import main


def test_every_option_of_every_command_has_help_and_commands_run_in_workflow_order():
    import argparse

    from usplat_dr.cli import COMMANDS, job_module

    missing = []
    for name in COMMANDS:
        parser = argparse.ArgumentParser()
        importlib.import_module(f"usplat_dr.jobs.{job_module(name)}").add_arguments(parser)
        missing += [f"usplat {name} {'/'.join(a.option_strings) or a.dest}"
                    for a in parser._actions
                    if not a.help and not isinstance(a, argparse._HelpAction)]
    assert not missing, missing
    # what a user does first comes first in `usplat --help`
    assert list(COMMANDS) == ["demo", "synth", "import", "pose", "train", "eval", "render", "view",
                              "export-ply", "models", "bench", "fit", "params", "render-demo",
                              "doctor"]


@pytest.mark.parametrize("module", ["synth", "import_", "fit"])
def test_image_shape_is_the_one_name_and_resolution_still_works_with_a_line(module, caplog):
    import argparse

    parser = argparse.ArgumentParser()
    importlib.import_module(f"usplat_dr.jobs.{module}").add_arguments(parser)
    required = {"synth": ["--out", "x"], "import_": ["--out", "x", "--colmap", "c"],
                "fit": []}[module]
    with caplog.at_level(logging.WARNING, logger="usplat_dr.jobs.arguments"):
        new = parser.parse_args([*required, "--image-shape", "8", "16"])
        assert not caplog.records
        old = parser.parse_args([*required, "--resolution", "8", "16"])
    assert new.image_shape == old.image_shape == [8, 16]
    assert "--resolution is now --image-shape" in caplog.text


def test_doctor_reports_and_succeeds_here():
    r = subprocess.run([sys.executable, "-m", "usplat_dr", "doctor"], capture_output=True,
                       text=True, timeout=300, check=False)
    assert r.returncode == 0, r.stdout + r.stderr
    for needle in ("drjit", "mitsuba", "torch", "numpy", "backends: ",
                   "threads", "LLVM min/max kernel: ok", "llvm_ad_rgb", "CUDA"):
        assert needle in r.stdout, needle
    # any suitable libLLVM: 19 here, 20 or later on newer machines
    loaded = re.search(r"loaded: libLLVM (\d+)\.", r.stdout)
    assert loaded and int(loaded.group(1)) >= 19, r.stdout
    # the pins (on: ``usplat`` turns them on), the OpenMP spin, the core keeper's probe and
    # what ``auto`` decides (on or off: it depends on the machine and its load)
    for needle in ("portable numerics: on (USPLAT_PORTABLE=1)", "ATEN_CPU_CAPABILITY=avx2",
                   "CPU code path: ", "OpenMP spin: GOMP_SPINCOUNT=",
                   "idle-core wake-up: ", "hypervisor flag: "):
        assert needle in r.stdout, needle
    # haswell, pinned, where the host has AVX2 and FMA; the host's target elsewhere
    assert re.search(r"Dr\.Jit LLVM target: \S+, \d+ float lanes \((not )?pinned", r.stdout)
    assert re.search(r"auto, a CPU run on \d+ core\(s\): core keeper (on|off): ", r.stdout)
    # the thread count usplat's commands would start with, and why
    assert re.search(r"usplat's commands start with threads: \d+ \(\d+ core\(s\) allowed", r.stdout)


def test_doctor_exits_nonzero_with_advice_without_llvm(tmp_path):
    import os

    env = dict(os.environ, DRJIT_LIBLLVM_PATH=str(tmp_path / "libLLVM-15.so.1"))
    (tmp_path / "libLLVM-15.so.1").write_bytes(b"")
    r = subprocess.run([sys.executable, "-m", "usplat_dr", "doctor"], capture_output=True,
                       text=True, timeout=300, env=env, check=False)
    assert r.returncode == 1
    assert "libllvm19" in r.stdout and "Problems" in r.stdout


def test_render_demo_writes_images(tmp_path, caplog):
    assert main(["-q", "render-demo", "--out", str(tmp_path), "--image-shape", "40", "48",
                 "--views", "2"]) == 0
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["contact_sheet.png"] + [f"view{v:02d}_{k}.png" for v in range(2)
                                             for k in ("alpha", "color", "depth")]
    color = np.asarray(Image.open(tmp_path / "view00_color.png"))
    assert color.shape == (40, 48, 3)
    assert color.std() > 10  # a scene, not a blank image
    # the old square --size still works for one release, with a line saying so
    with caplog.at_level(logging.WARNING, logger="usplat_dr.jobs.arguments"):
        assert main(["render-demo", "--out", str(tmp_path / "old"), "--size", "16",
                     "--views", "1"]) == 0
    assert np.asarray(Image.open(tmp_path / "old" / "view00_color.png")).shape == (16, 16, 3)
    assert "--size N is now --image-shape N N" in caplog.text
    alpha = np.asarray(Image.open(tmp_path / "view00_alpha.png"))
    assert 0 < (alpha > 128).mean() < 1  # foreground and sky


@pytest.mark.parametrize("argv, message", [
    (["render-demo", "--image-shape", "0", "8"],
     "--image-shape/--resolution: must be an integer >= 4, got '0'"),
    (["render-demo", "--size", "2"], "--size: must be an integer >= 4, got '2'"),
    (["synth", "--out", "x", "--frames", "2"], "--frames: must be an integer >= 3"),
    (["fit", "--iterations", "zero"], "--iterations: must be an integer >= 1, got 'zero'"),
    (["bench", "--prunes", "all,nope"], "--prunes: unknown ['nope']"),
    (["bench", "--configs", "tiny:z"], "--configs: 'tiny:z' is not preset:variant"),
    (["eval", "--checkpoint", "c", "--data", "d", "--device", "tpu"], "invalid choice: 'tpu'"),
    (["eval", "--checkpoint", "c", "--data", "d", "--precision", "fp16"],
     "invalid choice: 'fp16'"),
    (["eval", "--checkpoint", "c", "--data", "d", "--gaussians", "0"],
     "argument --gaussians: must be a count (an integer >= 1), a fraction in (0, 1]"),
    (["export-ply", "--checkpoint", "c", "--data", "d", "--gaussians", "1.5"],
     "argument --gaussians: must be a count"),
    (["render", "--checkpoint", "c", "--gaussians", "30%", "--rank-by", "size"],
     "argument --rank-by: invalid choice: 'size'"),
    (["eval", "--checkpoint", "c", "--data", "d", "--gaussians", "auto", "--tolerance", "-1"],
     "argument --tolerance: must be a number of dB >= 0"),
    (["bench", "--gaussians", "0.1,1.5"],
     "--gaussians/--fractions: must be a count (an integer >= 1)"),
    (["bench", "--fractions", "0.1,0"], "--gaussians/--fractions: must be a count"),
    (["bench", "--rank-by", "learned,size"], "--rank-by: unknown ['size']"),
    (["bench", "--checkpoint", "tiny:c=x.pt"], "--checkpoint: must be PRESET:VARIANT:TAG=PATH"),
    (["no-such-command"], "invalid choice: 'no-such-command'"),
])
def test_cli_rejects_bad_arguments_as_usage_errors(argv, message, capsys):
    # argparse checks types and choices: exit status 2 and the message, before any work
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_train_names_a_bad_config_value_and_where_it_was_set(capsys):
    assert main(["train", "--config", "synthetic_tiny.yaml", "train.steps=abc"]) == 2
    assert re.search(r"usplat train: error: train\.steps='abc': expected int.*"
                     r"command line \(train\.steps=abc\)", capsys.readouterr().err)


SHIPPED = str(Path(__file__).parents[2] / "checkpoints" / "tiny_baseline.pt")
FULL = str(Path(__file__).parents[2] / "checkpoints" / "tiny_full.pt")


@pytest.fixture(scope="module")
def one_scene(tmp_path_factory):
    from usplat_dr.data.synth import synthesize

    root = tmp_path_factory.mktemp("one_scene")
    synthesize(root, scenes=1, frames=10, resolution=(32, 32), seed=8, spp=4, stage="test",
               previews=0, progress=False, kinds=("indoor",))
    return root


#: The user mistakes README's "Errors" paragraph lists, each with the words its one line must
#: hold. ``{data}`` is a real one-scene synthetic set, ``{tmp}`` an empty folder.
MISTAKES = [
    (["eval", "--checkpoint", "{tmp}/missing.ckpt", "--data", "{data}"],
     "checkpoint '{tmp}/missing.ckpt' does not exist"),
    (["eval", "--checkpoint", "{tmp}/text.ckpt", "--data", "{data}"],
     "not a file written by torch.save"),
    (["eval", "--checkpoint", SHIPPED, "--data", "{tmp}/nowhere"],
     "--data: no evaluation_index_*.json"),
    (["export-ply", "--checkpoint", SHIPPED, "--data", "{data}", "--scene", "nope"],
     "scene 'nope' is not in"),
    (["export-ply", "--checkpoint", SHIPPED, "--data", "{data}", "--target", "9"],
     "--target must be in 0..1"),
    (["export-ply", "--checkpoint", SHIPPED, "--data", "{data}", "--gaussians", "0.3",
      "--rank-by", "learned"], "rank_by='learned' needs a model with an importance head"),
    (["export-ply", "--checkpoint", SHIPPED, "--data", "{data}", "--gaussians", "0.3",
      "--tolerance", "0.5"], "--tolerance applies to --gaussians auto only (got --gaussians 0.3)"),
    (["eval", "--checkpoint", SHIPPED, "--data", "{data}", "--tolerance", "0.5"],
     "--tolerance applies to --gaussians auto only (got --gaussians None): add --gaussians auto"),
    (["train", "--config", "{tmp}/missing.yaml"],
     "config file '{tmp}/missing.yaml' does not exist"),
    (["train", "--config", "synthetic_tiny.yaml", "train.stepz=3"], "unknown key 'train.stepz'"),
    (["train", "--config", "synthetic_tiny.yaml", "dataset.roots=[{tmp}/nowhere]"],
     "dataset root {tmp}/nowhere does not exist"),
    (["train", "--config", "synthetic_tiny.yaml", "dataset.roots=[{data}]",
      "model.init_from={tmp}/missing.pt"],
     "model.init_from: checkpoint '{tmp}/missing.pt' does not exist"),
    (["train", "--config", "synthetic_tiny.yaml", "dataset.roots=[{data}]",
      "model.variant=agnostic", f"model.init_from={FULL}"],
     ("holds variant 'full' with another configuration than this model's; start from a "
      "baseline (a)")),
    (["fit", "--data", "{tmp}/nowhere"], "index.json does not exist"),
]


@pytest.mark.parametrize("argv, needle", MISTAKES, ids=[" ".join(m[0][:2]) + f" {i}"
                                                         for i, m in enumerate(MISTAKES)])
def test_user_mistakes_end_in_one_line_and_status_2(argv, needle, one_scene, tmp_path, capsys,
                                                     caplog):
    caplog.set_level(logging.ERROR, logger="usplat_dr.model.hypernet.resnet")
    (tmp_path / "text.ckpt").write_text("not a checkpoint")

    def fill(text):
        return text.replace("{tmp}", str(tmp_path)).replace("{data}", str(one_scene))

    assert main(["-q", *map(fill, argv)]) == 2
    err = capsys.readouterr().err.strip()
    command = argv[0]
    assert fill(needle) in err, err
    assert err.startswith(f"usplat {command}: error: ") and "Traceback" not in err
    assert len(err.splitlines()) == 1, err


@pytest.mark.parametrize("gaussians, expected", [("100", 100), ("25%", 512)])
def test_export_ply_writes_the_budgeted_gaussians(gaussians, expected, one_scene, tmp_path,
                                                  caplog):
    # 2 context views of 32x32 pixels: 2048 Gaussians per target; the shipped (a) has no
    # importance head, so the budget keeps the most opaque, and says so
    from usplat_dr.model.ply import read_ply

    caplog.set_level(logging.WARNING, logger="usplat_dr.model.uniquesplat")
    out = tmp_path / "g.ply"
    assert main(["-q", "export-ply", "--checkpoint", SHIPPED, "--data", str(one_scene),
                 "--image-shape", "32", "32", "--gaussians", gaussians, "--out", str(out)]) == 0
    assert read_ply(out)["means"].shape == (expected, 3)
    assert any("no importance head" in r.message for r in caplog.records)
    # a standard 3DGS viewer's reader (plyfile, a test extra: as the graphdeco viewers read it)
    assert plyfile.PlyData.read(str(out))["vertex"].count == expected


def test_gaussians_auto_chooses_per_scene_and_eval_writes_the_choice(one_scene, tmp_path,
                                                                      capsys):
    import csv
    import json

    out = tmp_path / "g.ply"
    assert main(["-q", "export-ply", "--checkpoint", SHIPPED, "--data", str(one_scene),
                 "--image-shape", "32", "32", "--gaussians", "auto", "--tolerance", "1",
                 "--out", str(out)]) == 0
    assert "chosen by the automatic count" in capsys.readouterr().out
    assert plyfile.PlyData.read(str(out))["vertex"].count <= 2 * 32 * 32
    ev = tmp_path / "eval"
    assert main(["-q", "eval", "--checkpoint", SHIPPED, "--data", str(one_scene),
                 "--image-shape", "32", "32", "--gaussians", "auto", "--out", str(ev)]) == 0
    with open(ev / "per_scene.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows and all(0 < float(r["auto_keep"]) <= 1 for r in rows)
    # the Gaussians each target kept are the chosen fraction of the 2 x 32 x 32 predicted
    for r in rows:
        keep = float(r["auto_keep"])
        expected = 2048 if keep == 1 else round(keep * 2048)
        assert int(r["gaussians_kept"]) == expected
        assert float(r["gaussians_rendered"]) <= expected
    summary = json.loads((ev / "summary.json").read_text())
    assert summary["gaussians"] == {"auto": {"tolerance_db": 0.2, "merge": True}}
    assert summary["rank_by"] == "dither"  # the automatic count's default ranking
    assert summary["splits"]["standard"]["mean_auto_keep"] == pytest.approx(
        sum(float(r["auto_keep"]) for r in rows if r["split"] == "standard")
        / sum(r["split"] == "standard" for r in rows))


def test_debug_shows_the_traceback(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.ckpt"):
        main(["--debug", "-q", "render", "--checkpoint", str(tmp_path / "missing.ckpt"),
              "--data", str(tmp_path), "--index", "x.json"])


def test_cli_commands_are_a_table_of_job_modules():
    from usplat_dr.cli import COMMANDS

    for name in ("demo", "bench", "train", "eval", "render", "export-ply", "render-demo",
                 "fit", "synth", "params", "doctor", "import"):
        assert name in COMMANDS
    with pytest.raises(SystemExit) as exit_info:  # each command's own arguments
        main(["train", "--help"])
    assert exit_info.value.code == 0


def modules_with_examples() -> list[str]:
    """Every library module whose source holds a ``>>>`` example (found, not listed by hand:
    a new example is run from the day it is written)."""
    root = Path(usplat_dr.__file__).parent
    found = []
    for path in sorted(root.rglob("*.py")):
        if ">>>" in path.read_text():
            parts = path.relative_to(root.parent).with_suffix("").parts
            found.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return found


@pytest.mark.parametrize("module", modules_with_examples())
def test_docstring_examples_run(module):
    result = doctest.testmod(importlib.import_module(module))
    assert result.attempted > 0 and result.failed == 0


def test_version_and_help_state_the_defaults(capsys):
    import usplat_dr

    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"usplat-dr {usplat_dr.__version__}"
    for command, shown in (("render", ["(default: 60)", "(default: outputs/render/video)",
                                       "(default: orbit)", "(default: cpu)"]),
                           ("eval", ["(default: cpu)"]),
                           ("bench", ["(default: all, cull,", "(default: cpu)"])):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
        assert all(s in text for s in shown), (command, text)
        # unset values and flags say nothing; a default the help words itself is said once
        assert "(default: None)" not in text and "(default: False)" not in text
        assert "Settings(" not in text and "Config(" not in text and "{'" not in text
