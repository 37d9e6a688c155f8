"""``usplat train`` under a real ``torchrun --nproc_per_node 2`` (gloo, CPU) on a one-chunk
synthetic set: both ranks train on their own scenes and end with identical parameters, rank 0
writes the one checkpoint, SIGTERM to the launcher stops every rank after the same step with a
checkpoint, ``--resume`` continues it exactly, and a rank that fails ends the run with one
message naming it.

Each run starts two Python processes that import torch and Dr.Jit (about 15 s on one core),
so the runs are few and tiny: 32x32 images, a handful of steps, one thread per rank."""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from usplat_dr.data.synth import synthesize
from usplat_dr.training.checkpoints import load_model
from usplat_dr.training.distributed import parameter_digest

REPO = Path(__file__).parents[2]
CONFIG = REPO / "usplat_dr" / "configs" / "synthetic_tiny.yaml"
STEPS = 20  # the straight run's length, and where the signalled run resumes to

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def one_chunk(tmp_path_factory) -> Path:
    """Three scenes in one chunk: before scene sharding, rank 1 got no data at all."""
    root = tmp_path_factory.mktemp("synth")
    synthesize(root, scenes=3, frames=10, resolution=(32, 32), seed=0, spp=4, stage="train",
               previews=0, progress=False, kinds=("indoor",))
    assert len(list((root / "train").glob("*.torch"))) == 1
    return root


def command(root: Path, out: Path, steps: int, *extra: str) -> list[str]:
    # `python -m torch.distributed.run` and `-m usplat_dr`: this interpreter and this checkout
    return [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node",
            "2", "-m", "usplat_dr", "train", "--config", str(CONFIG),
            f"dataset.roots=[{root}]", "dataset.image_shape=[32,32]", f"output_dir={out}",
            f"train.steps={steps}", "train.progress=false", "train.log_every=1", "threads=1",
            "train.validate_every=100000", "dataset.view_sampler.num_target_views=2",
            "dataset.view_sampler.min_distance_between_context_views=3",
            "dataset.view_sampler.max_distance_between_context_views=6",
            "dataset.view_sampler.initial_min_distance_between_context_views=3",
            "dataset.view_sampler.initial_max_distance_between_context_views=6", *extra]


def environment() -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}


def torchrun(*args: str | Path, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(command(*args), env=environment(), capture_output=True, text=True,
                          timeout=300, check=False, **kwargs)


def results(stdout: str) -> dict[int, dict]:
    """Each rank's printed result (one JSON line per rank), by rank."""
    found = [json.loads(line) for line in stdout.splitlines() if line.startswith("{")]
    return {r["rank"]: r for r in found}


@pytest.fixture(scope="module")
def straight(one_chunk, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("straight")
    run = torchrun(one_chunk, out, STEPS)
    assert run.returncode == 0, run.stderr[-3000:]
    return out, results(run.stdout)


def test_two_ranks_train_one_chunk_to_identical_parameters(straight):
    out, by_rank = straight
    assert sorted(by_rank) == [0, 1] and {r["step"] for r in by_rank.values()} == {STEPS}
    # Equal digests: bit for bit the same parameters on both ranks (DDP's averaged gradients)
    assert by_rank[0]["params_sha256"] == by_rank[1]["params_sha256"]
    # Rank 0's scenes are not rank 1's: the losses differ (they would match if both ranks
    # read the same examples)
    assert by_rank[0]["loss"] != by_rank[1]["loss"]
    # one checkpoint, written by rank 0, holding those parameters and each rank's position
    assert os.listdir(out / "checkpoints") == ["last.ckpt"]
    model, _ = load_model(out / "checkpoints" / "last.ckpt")
    assert parameter_digest(model) == by_rank[0]["params_sha256"]
    state = torch.load(out / "checkpoints" / "last.ckpt", weights_only=False)
    assert state["step"] == STEPS and len(state["ranks"]) == 2
    rows = (out / "metrics.csv").read_text().splitlines()[1:]
    assert [int(r.split(",")[0]) for r in rows] == list(range(1, STEPS + 1))  # rank 0 only


def test_sigterm_stops_every_rank_at_one_step_and_resume_continues_exactly(
        one_chunk, straight, tmp_path):
    out = tmp_path / "run"
    log = tmp_path / "stderr.txt"
    with open(log, "w") as err:  # a file, not a pipe: nothing blocks while we wait
        launcher = subprocess.Popen(command(one_chunk, out, STEPS), env=environment(),
                                    stdout=subprocess.DEVNULL, stderr=err)
    metrics = out / "metrics.csv"
    deadline = time.monotonic() + 240  # a guard against a hang, not a timing assertion
    try:
        while not (metrics.is_file() and len(metrics.read_text().splitlines()) >= 3):
            assert launcher.poll() is None, log.read_text()[-3000:]
            assert time.monotonic() < deadline, "no training step in 240 s"
            time.sleep(0.2)
        launcher.send_signal(signal.SIGTERM)  # what a cluster scheduler sends before it kills
        launcher.wait(timeout=240)
    finally:
        if launcher.poll() is None:
            launcher.kill()
    stderr = log.read_text()
    stops = re.findall(r"rank (\d) stopped by signal 15 at step (\d+)", stderr)
    assert sorted(rank for rank, _ in stops) == ["0", "1"], stderr[-3000:]
    (stopped,) = {int(step) for _, step in stops}  # both ranks after the same step
    assert 2 <= stopped < STEPS
    state = torch.load(out / "checkpoints" / "last.ckpt", weights_only=False)
    assert state["step"] == stopped
    # each rank's data position, saved by rank 0; the shards are padded to equal length, so
    # both ranks are at the same epoch and batch
    assert [r["data"] for r in state["ranks"]] == [state["data"]] * 2

    resumed = torchrun(one_chunk, out, STEPS, "--resume")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert resumed.stderr.count(f"at step {stopped}") >= 2  # "resumed from ... at step N"
    by_rank = results(resumed.stdout)
    assert {r["step"] for r in by_rank.values()} == {STEPS} and len(by_rank) == 2
    # one thread per rank and gloo's fixed summation order: the resumed run ends with the
    # uninterrupted run's parameters bit for bit (any data or RNG state off would change them)
    assert {r["params_sha256"] for r in by_rank.values()} == \
        {straight[1][0]["params_sha256"]}


def test_a_failing_rank_ends_the_run_with_one_message(one_chunk, tmp_path):
    # two chunks of one scene each; one is unreadable, so the rank whose shard it is has no
    # example at all and fails at its first batch, while the other is inside a collective
    root = tmp_path / "data"
    shutil.copytree(one_chunk, root)
    stage = root / "train"
    index = json.loads((stage / "index.json").read_text())
    first, second, _third = sorted(index)
    (stage / "000001.torch").write_bytes(b"not a chunk")
    (stage / "index.json").write_text(json.dumps({first: "000000.torch",
                                                  second: "000001.torch"}))
    torch.save([s for s in torch.load(stage / "000000.torch") if s["key"] == first],
               stage / "000000.torch")
    run = torchrun(root, tmp_path / "out", 5)
    assert run.returncode != 0
    lines = [line for line in run.stderr.splitlines() if line.startswith("usplat train: ")]
    assert len(lines) == 1, run.stderr[-3000:]  # one message, from the failing rank
    assert re.fullmatch(r"usplat train: rank [01] of 2 failed at step 0: ConfigError: the "
                        r"training set yields no examples.*", lines[0])
    assert "Connection closed by peer" not in run.stderr  # not the other rank's gloo error
    # the only traceback is torchrun's own (its ChildFailedError summary), none from a worker
    assert run.stderr.count("Traceback (most recent call last)") == 1, run.stderr[-3000:]
    # torchrun's closing summary names the cause too (its error file)
    assert lines[0].removeprefix("usplat train: ") in run.stderr.split("Root Cause")[1]
