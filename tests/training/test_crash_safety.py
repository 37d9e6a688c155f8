"""Crash safety with real signals: a real ``usplat train`` process is killed with SIGKILL at
random moments (8 times, some of them while a checkpoint is being written) and stopped with
real SIGTERM and SIGINT; every restart with ``--resume`` finds a valid checkpoint at a step no
earlier than the last one, and the run ends with the same parameters, bit for bit, as an
uninterrupted run (one thread: a fixed order of float sums).

Each start imports torch and Dr.Jit and builds the model (a few seconds on one core), so the
steps are tiny: 32x32 images, 2 targets, a checkpoint after every step."""

import csv
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from tests.training.processes import environment, stamp, wait_for

REPO = Path(__file__).parents[2]
CONFIG = REPO / "usplat_dr" / "configs" / "synthetic_tiny.yaml"
#: Steps of the run. Each of the 8 kills lets the run advance by one step (the checkpoint it
#: waits for) plus a random delay of at most two step times, so the kills use at most 24 steps
#: and about 16 on average: SIGTERM and SIGINT always meet a run that is still training. (20
#: kills of an 80-step run until 2026-12-04: 140 s of the suite's 15 minutes; 8 keep two kills
#: mid-write, the 1st and 5th.)
STEPS = 36
KILLS = 8

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def data(trainer_set) -> Path:
    return trainer_set


def command(root: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "usplat_dr", "-q", "train", "--config", str(CONFIG),
            "--resume", f"dataset.roots=[{root}]", "dataset.image_shape=[32,32]",
            f"output_dir={out}", f"train.steps={STEPS}", "train.progress=false",
            "train.checkpoint_every=1", "train.log_every=1", "threads=1",
            "train.validate_every=100000", "dataset.view_sampler.num_target_views=2",
            "dataset.view_sampler.min_distance_between_context_views=3",
            "dataset.view_sampler.max_distance_between_context_views=6",
            "dataset.view_sampler.initial_min_distance_between_context_views=3",
            "dataset.view_sampler.initial_max_distance_between_context_views=6"]


def checkpoint_step(out: Path) -> int:
    """The step of the run's checkpoint, which must always be complete and loadable."""
    path = out / "checkpoints" / "last.ckpt"
    if not path.exists():
        return 0
    return torch.load(path, map_location="cpu", weights_only=True)["step"]


def weights(out: Path) -> dict:
    return torch.load(out / "checkpoints" / "last.ckpt", map_location="cpu",
                      weights_only=True)["model"]


def test_killed_and_signalled_runs_resume_to_the_uninterrupted_result(data, tmp_path):
    rng = random.Random(0)
    straight = tmp_path / "straight"
    subprocess.run(command(data, straight), env=environment(), check=True, timeout=600,
                   capture_output=True)
    assert checkpoint_step(straight) == STEPS
    step_s = seconds_per_step(straight)

    out = tmp_path / "killed"
    ckpt_dir = out / "checkpoints"
    kills, during_write, stops, last_step = 0, 0, 0, 0
    # SIGKILL 8 times, then SIGTERM and SIGINT once each, then run to the end
    plan = [signal.SIGKILL] * KILLS + [signal.SIGTERM, signal.SIGINT, None]
    for n, sig in enumerate(plan):
        proc = subprocess.Popen(command(data, out), env=environment(), stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE)
        start_step = last_step
        try:
            if sig is None:
                _, err = proc.communicate(timeout=600)
                assert proc.returncode == 0, err.decode()[-2000:]
                break
            # wait until this process has written a checkpoint of its own (it has resumed
            # and trained), then strike: every 4th kill as soon as a checkpoint's temporary
            # file appears (mid-write), the others after a random delay within two steps
            # (measured on the uninterrupted run, so a faster CPU does not finish the run)
            before = stamp(ckpt_dir / "last.ckpt")
            if not wait_for(lambda: stamp(ckpt_dir / "last.ckpt") != before, proc):  # noqa: B023 (called in this iteration)
                pytest.fail(f"run {n} ended before it was signalled: "
                            f"{proc.communicate()[1].decode()[-2000:]}")
            if sig == signal.SIGKILL and n % 4 == 0:
                if wait_for(lambda: any(ckpt_dir.glob(".last.ckpt.*.tmp")), proc):
                    during_write += 1
            else:
                time.sleep(rng.uniform(0.0, 2 * step_s))
            proc.send_signal(sig)
            _, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        if sig == signal.SIGKILL:
            kills += 1
        else:  # saved and stopped cleanly, saying so
            assert proc.returncode == 0, err.decode()[-2000:]
            assert "stopped by signal" in err.decode()
            stops += 1
        step = checkpoint_step(out)  # complete and loadable whatever the moment of the kill
        assert start_step <= step <= STEPS
        last_step = step
    assert kills == KILLS and stops == 2 and during_write >= 1
    assert checkpoint_step(out) == STEPS
    a, b = weights(straight), weights(out)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def seconds_per_step(out: Path) -> float:
    """The uninterrupted run's time per step after its first (metrics.csv, ``time_s``)."""
    with open(out / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    first, last = rows[0], rows[-1]
    return (float(last["time_s"]) - float(first["time_s"])) / (int(last["step"])
                                                              - int(first["step"]))
