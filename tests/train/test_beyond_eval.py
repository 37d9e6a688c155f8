"""train/studies/beyond_eval.sh: a run's kept state is exported as float16 shipped weights and
scored by `usplat eval` on the named splits; a second call keeps what is written; a run with
no kept state is named and fails the call."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import torch

from usplat_dr.training.checkpoints import resolve_checkpoint

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "beyond_eval.sh"


def _run(env, *names, timeout=600):
    return subprocess.run(["bash", str(SCRIPT), *names], env=env, capture_output=True,
                          text=True, timeout=timeout, check=False)


def test_a_kept_state_is_exported_and_scored_once(tmp_path, protocol_set):
    # a run folder whose step-300 state is the shipped (a) (a usplat weights file: the
    # export reads it as it reads a training checkpoint)
    kept = tmp_path / "runs" / "baseline_seed_7" / "checkpoints" / "step_0000300.ckpt"
    kept.parent.mkdir(parents=True)
    shutil.copy(resolve_checkpoint("tiny_baseline"), kept)
    env = {**os.environ, "PYTHON": sys.executable, "OUT": str(tmp_path / "runs"),
           "DATA": str(protocol_set), "EVAL": str(tmp_path / "eval"), "SPLITS": "standard"}
    proc = _run(env, "baseline_seed_7")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    weights = kept.parents[1] / "step_0000300.pt"
    state = torch.load(weights, map_location="cpu", weights_only=True)
    floats = [v for v in state["model"].values() if v.is_floating_point()]
    assert floats and all(v.dtype == torch.float16 for v in floats)
    summary = json.loads((tmp_path / "eval" / "eval_baseline_seed_7" / "summary.json")
                         .read_text())
    assert set(summary["splits"]) == {"standard"}
    assert summary["splits"]["standard"]["scenes"] >= 1
    assert (tmp_path / "eval" / "eval_baseline_seed_7" / "per_scene.csv").is_file()
    # the evaluation's log lies beside the run, not among the scores (which get committed)
    assert (tmp_path / "runs" / "baseline_seed_7.eval.log").is_file()
    assert not list((tmp_path / "eval").glob("*.log"))
    assert not (tmp_path / "eval" / "eval_baseline_seed_7" / "renders").exists()
    assert list((tmp_path / "runs" / "baseline_seed_7.renders").rglob("*.png"))
    again = _run(env, "baseline_seed_7", timeout=60)
    assert again.returncode == 0 and "already scored" in again.stdout


def test_a_run_without_its_kept_state_is_named(tmp_path):
    env = {**os.environ, "OUT": str(tmp_path / "runs"), "EVAL": str(tmp_path / "eval")}
    proc = _run(env, "full_seed_3", timeout=60)
    assert proc.returncode == 1
    assert "full_seed_3: no step-300 checkpoint" in proc.stdout
    assert not (tmp_path / "eval").exists()


def test_dry_run_prints_one_thread_evaluations(tmp_path):
    (tmp_path / "runs" / "full_seed_0" / "checkpoints").mkdir(parents=True)
    (tmp_path / "runs" / "full_seed_0" / "checkpoints" / "step_0000300.ckpt").write_bytes(b"")
    env = {**os.environ, "OUT": str(tmp_path / "runs"), "EVAL": str(tmp_path / "eval"),
           "DATA": "outputs/big128/test5000", "DRY_RUN": "1"}
    proc = _run(env, "full_seed_0", timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    line = proc.stdout.strip()
    assert line.startswith("full_seed_0: export ") and "USPLAT_THREADS=1 " in line
    assert "--splits standard wide_baseline extrapolation" in line
    assert "--data outputs/big128/test5000" in line
    assert not (tmp_path / "eval").exists()
