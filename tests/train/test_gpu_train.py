"""train/studies/gpu_train.sh (``scripts/run.sh gpu-train``), the GPU job one octave up, run on
the CPU at a tiny size: it unpacks the carried sets, fine-tunes the half-size model at the
full size, brings its state and a shippable .pt back, and scores it against the half-size
model's renders upsampled."""

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).parents[2]
SCRIPT = ROOT / "train" / "studies" / "gpu_train.sh"
spec = importlib.util.spec_from_file_location("carry_sets",
                                              ROOT / "train" / "studies" / "carry_sets.py")
carry = importlib.util.module_from_spec(spec)
spec.loader.exec_module(carry)


@pytest.mark.slow
def test_the_gpu_training_job_runs_on_the_cpu_at_a_tiny_size(tmp_path, trainer_set,
                                                              protocol_set):
    packed = tmp_path / "gpudata"
    carry.main(["pack", "--out", str(packed), f"train={trainer_set / 'train'}",
                f"heldout={protocol_set}::png"])
    out, work = tmp_path / "out", tmp_path / "work"
    env = {**os.environ, "PYTHON": sys.executable, "DEVICE": "cpu", "SIZE": "32",
           "INIT": "tiny_baseline", "BATCH": "1", "GPUDATA": str(packed), "WORK": str(work),
           "CHECKPOINT_EVERY": "1", "HELDOUT_SCENES": "1"}
    proc = subprocess.run(["bash", str(SCRIPT), str(out), "300", "2"], env=env,
                          capture_output=True, text=True, timeout=1200, cwd=tmp_path,
                          check=False)
    log = proc.stdout[-3000:] + proc.stderr[-3000:]
    assert proc.returncode == 0, log
    state = torch.load(out / "last.ckpt", map_location="cpu", weights_only=True)
    assert state["step"] == 2, log
    config = state["config"]
    assert tuple(config["dataset"]["image_shape"]) == (32, 32)
    assert config["model"]["init_from"] == "tiny_baseline"
    assert config["model"]["variant"] == "baseline"
    shipped = torch.load(out / "model.pt", map_location="cpu", weights_only=True)
    assert shipped  # the exported weights load without unpickling code
    summary = json.loads((out / "eval" / "summary.json").read_text())
    assert summary["size"] == 32 and summary["scenes"] == 1
    assert summary["model32"] == str(out / "model.pt") and summary["model16"] == "tiny_baseline"
    assert "psnr_16_up" in summary["means"] and (out / "eval" / "comparison.png").is_file()
    assert (out / "metrics.csv").is_file() and "training:" in proc.stdout


def test_the_gpu_training_job_says_what_is_missing(tmp_path):
    env = {**os.environ, "PYTHON": sys.executable, "GPUDATA": str(tmp_path / "none"),
           "WORK": str(tmp_path / "work")}
    proc = subprocess.run(["bash", str(SCRIPT), str(tmp_path / "out")], env=env,
                          capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 2
    assert "gpu-prepare" in proc.stdout and "none/train" in proc.stdout
