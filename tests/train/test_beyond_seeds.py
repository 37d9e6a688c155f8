"""train/studies/beyond_seeds.sh: each seed trains with extrapolated targets until its kept
step, is stopped there, and a second call leaves it as it is."""

import os
import subprocess
from pathlib import Path

import pytest
import torch

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "beyond_seeds.sh"


@pytest.mark.slow
def test_seeds_stop_at_their_kept_step_with_targets_beyond(tmp_path, trainer_set):
    import sys

    env = {**os.environ, "PYTHON": sys.executable, "OUT": str(tmp_path / "runs"),
           "STOP": "20", "KEEP": "20", "CKPT_EVERY": "10", "DATA": str(trainer_set),
           "JOBS": "2"}
    proc = subprocess.run(["bash", str(SCRIPT), "3", "4"], env=env, capture_output=True,
                          text=True, timeout=1200, check=False)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    for seed in (3, 4):
        kept = tmp_path / "runs" / f"seed_{seed}" / "checkpoints" / "step_0000020.ckpt"
        state = torch.load(kept, map_location="cpu", weights_only=True)
        config = state["config"]
        assert state["step"] == 20 and config["seed"] == seed
        sampler = config["dataset"]["view_sampler"]
        assert sampler["max_distance_beyond_context_views"] == 4
        assert config["train"]["steps"] == 6000  # the schedule, cut at STOP
        last = torch.load(kept.parent / "last.ckpt", map_location="cpu", weights_only=True)
        assert 20 <= last["step"] < 70  # stopped soon after the kept step (polled every 5 s)
    again = subprocess.run(["bash", str(SCRIPT), "3"], env=env, capture_output=True,
                           text=True, timeout=600, check=False)
    assert again.returncode == 0 and "already kept" in again.stdout


@pytest.mark.parametrize("shape, expected", [("128 128", "dataset.image_shape=[128,128]"),
                                             ("", None)])
def test_the_start_and_image_shape_are_passed_on(tmp_path, shape, expected):
    env = {**os.environ, "OUT": str(tmp_path / "runs"), "DRY_RUN": "1", "ARM": "full",
           "INIT": "tiny_baseline_128", "IMAGE_SHAPE": shape, "DATA": "outputs/big128/x"}
    proc = subprocess.run(["bash", str(SCRIPT), "0", "1"], env=env, capture_output=True,
                          text=True, timeout=60, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = sorted(proc.stdout.splitlines())
    assert [line.split(":")[0] for line in lines] == ["seed 0", "seed 1"]
    for line in lines:
        assert "model.init_from=tiny_baseline_128 model.variant=full" in line
        assert "dataset.roots=[outputs/big128/x]" in line
        assert (expected in line) if expected else "dataset.image_shape" not in line
    assert not (tmp_path / "runs" / "full_seed_0").exists()  # nothing ran


def test_a_malformed_image_shape_is_refused(tmp_path):
    env = {**os.environ, "OUT": str(tmp_path), "DRY_RUN": "1", "IMAGE_SHAPE": "128"}
    proc = subprocess.run(["bash", str(SCRIPT), "0"], env=env, capture_output=True, text=True,
                          timeout=60, check=False)
    assert proc.returncode == 2 and "IMAGE_SHAPE must be two numbers" in proc.stdout


def test_runs_keep_large_blocks_in_the_heap_unless_the_caller_says(tmp_path):
    # glibc's thresholds (read at a process's start): 4 GiB by default, the caller's if set
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    env.update({"OUT": str(tmp_path), "DRY_RUN": "1"})
    proc = subprocess.run(["bash", str(SCRIPT), "0"], env=env, capture_output=True, text=True,
                          timeout=60, check=False)
    assert "MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=4294967296" in proc.stdout
    env["MALLOC_MMAP_THRESHOLD_"] = "131072"
    proc = subprocess.run(["bash", str(SCRIPT), "0"], env=env, capture_output=True, text=True,
                          timeout=60, check=False)
    assert "MALLOC_MMAP_THRESHOLD_=131072 " in proc.stdout
