"""train/studies/live_branch_gpu.sh, the GPU job, run on the CPU at a tiny size: it unpacks
the carried sets, trains an arm with the seed it is given, meters the arm and the start, and
brings the arm's whole state and the results back."""

import importlib.util
import json
import os
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).parents[2]
SCRIPT = ROOT / "train" / "studies" / "live_branch_gpu.sh"
spec = importlib.util.spec_from_file_location("carry_sets",
                                              ROOT / "train" / "studies" / "carry_sets.py")
carry = importlib.util.module_from_spec(spec)
spec.loader.exec_module(carry)


@pytest.mark.slow
def test_the_gpu_job_runs_on_the_cpu_at_a_tiny_size(tmp_path, trainer_set):
    packed = tmp_path / "gpudata"
    carry.main(["pack", "--out", str(packed), f"train={trainer_set / 'train'}",
                f"heldout={trainer_set}::png"])
    out, work = tmp_path / "out", tmp_path / "work"
    env = {**os.environ, "PYTHON": sys.executable, "BATCH": "2", "SEEDS": "1 2",
           "ARMS": "branch_primary_b32", "GPUDATA": str(packed), "WORK": str(work),
           "KEEP_EVERY": "1", "CHECKPOINT_EVERY": "1", "KEEP_BACK": "1"}
    proc = subprocess.run(["bash", str(SCRIPT), str(out), "300", "2", "cpu"], env=env,
                          capture_output=True, text=True, timeout=1200, cwd=tmp_path,
                          check=False)
    log = proc.stdout[-3000:] + proc.stderr[-3000:]
    assert proc.returncode == 0, log
    for seed in (1, 2):  # both seeds ran side by side, each with its own seed
        run = f"branch_primary_b32_s{seed}"
        state = torch.load(out / f"{run}.ckpt", map_location="cpu", weights_only=True)
        assert state["step"] == 2, log
        config = state["config"]
        assert config["seed"] == seed and config["dataset"]["overrides"]["seed"] == seed
        assert config["data_loader"]["batch_size"] == 4  # 2 x BATCH
        assert config["model"]["overrides"]["view_features"] == "primary"
        kept = torch.load(out / f"{run}_step1.ckpt", map_location="cpu", weights_only=True)
        assert kept["step"] == 1  # KEEP_BACK's step, not the last
    meter = json.loads((work / "meter" / "meter.json").read_text())
    assert set(meter) == {"tiny_full"} | {str(work / f"branch_primary_b32_s{s}") for s in (1, 2)}
    assert {"train", "heldout"} <= set(meter["tiny_full"])
    with tarfile.open(out / "results.tar.gz") as tar:
        names = tar.getnames()
    assert "./branch_primary_b32_s1/metrics.csv" in names and "./meter/meter.json" in names
    assert not any(n.endswith(".ckpt") for n in names)  # the states come back beside it
