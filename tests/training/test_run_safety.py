"""Run safety: a run keeps its results and everyday mistakes end as one line.

metrics.csv survives a SIGKILL right after ``--resume``; a run holds its output folder (a second
``usplat train`` there stops with status 2, naming the first's pid; a SIGKILLed run leaves no
stale lock); temporary files of killed writes are removed when the next run takes the folder;
a diverging run stops with its last good checkpoint; a changed model, a damaged checkpoint, a
shrunk training set, absurd threads or view-sampler values, a file as output_dir and a full
disk each end with one line naming the value and the fix (status 2); a path stored in a
checkpoint is never opened when it is loaded.

Runs are tiny (32x32 images of a 3-scene fake set, the baseline tiny model, one thread): a
real ``usplat train`` process starts in a few seconds, an in-process step takes ~0.1 s."""

import collections
import csv
import errno
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.data.fakes import fake_scene, write_plain_dataset
from tests.training.processes import environment, stamp, stop, wait_for
from usplat_dr.cli import main
from usplat_dr.config import load_config
from usplat_dr.training import Trainer, TrainingStopped
from usplat_dr.training.checkpoints import load_model

REPO = Path(__file__).parents[2]
COUNTS = collections.Counter()  # what the process-fault tests saw; printed by the last test
pytestmark = pytest.mark.usefixtures("restore_threads")


def write_data(root: Path, scenes: int) -> Path:
    """A fake set of ``scenes`` scenes of 10 frames at 32x32 (train and test stages)."""
    made = [fake_scene(f"scene{i}", 10, shape=(32, 32), fmt="png", seed=i) for i in range(scenes)]
    for stage in ("train", "test"):
        write_plain_dataset(root, stage, [made])
    return root


def overrides(root: Path, out: Path, steps: int, *extra: str) -> list[str]:
    # dtu: fixed near/far and any image shape (the fake scenes have no near/far records)
    return [f"dataset.roots=[{root}]", "dataset.name=dtu", "dataset.image_shape=[32,32]",
            f"output_dir={out}", f"train.steps={steps}", "train.progress=false",
            "train.validate_every=100000", "train.log_every=1", "train.checkpoint_every=1",
            "threads=1", "keep_cores_awake=false", "model.variant=baseline",
            "dataset.view_sampler.num_target_views=1",
            "dataset.view_sampler.min_distance_between_context_views=3",
            "dataset.view_sampler.max_distance_between_context_views=6",
            "dataset.view_sampler.initial_min_distance_between_context_views=3",
            "dataset.view_sampler.initial_max_distance_between_context_views=6", *extra]


#: The schedule of the ``trained`` run (a resume must pass the run's train.steps).
RUN_STEPS = 4


def usplat_train(*args: str) -> list[str]:
    return ["-q", "train", "--config", "synthetic_tiny.yaml", *args]


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_data(tmp_path_factory.mktemp("data"), scenes=3)


@pytest.fixture(scope="module")
def trained(data, tmp_path_factory) -> Path:
    """A run folder stopped after 2 of its ``RUN_STEPS`` steps (a checkpoint at step 2,
    metrics rows 1 and 2), as a killed run leaves it: resumes pass the same schedule."""
    import drjit as dr

    class StopAfterTwo(Trainer):
        def after_step(self, stats, last, run_log):
            return super().after_step(stats, last, run_log) or self.step >= 2

    out = tmp_path_factory.mktemp("trained")
    torch_threads, dr_threads = torch.get_num_threads(), dr.thread_count()
    StopAfterTwo(load_config(["synthetic_tiny.yaml"], overrides(data, out, RUN_STEPS))).fit()
    torch.set_num_threads(torch_threads)  # the trainer set them to 1 (threads=1)
    dr.set_thread_count(dr_threads)
    return out


@pytest.fixture
def run(trained, tmp_path) -> Path:
    """A copy of ``trained`` to change."""
    return Path(shutil.copytree(trained, tmp_path / "run"))


def one_line_error(capsys, status: int) -> str:
    """The error ``usplat`` printed (exactly one line on stderr), given its exit ``status``."""
    err = capsys.readouterr().err.strip()
    assert status == 2, err
    assert err.startswith("usplat train: error:") and "\n" not in err, err
    COUNTS["everyday mistakes: one line, exit 2"] += 1
    return err


def rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# ---- 1. metrics.csv survives a kill right after resume -----------------------------------------

def test_metrics_rows_survive_a_kill_right_after_resume(data, run):
    metrics = run / "metrics.csv"
    before = rows(metrics)
    assert [r["step"] for r in before] == ["1", "2"]
    proc = subprocess.Popen([sys.executable, "-m", "usplat_dr",
                             *usplat_train("--resume", *overrides(data, run, RUN_STEPS))],
                            env=environment(), stderr=subprocess.PIPE)
    try:
        # the first write of metrics.csv after the resume: strike at once
        old = stamp(metrics)
        changed = wait_for(lambda: stamp(metrics) != old, proc)
    finally:
        err = stop(proc)
    assert changed and proc.returncode == -signal.SIGKILL, err[-2000:]
    COUNTS["SIGKILL right after resume"] += 1
    COUNTS["metrics rows lost"] += sum(r not in rows(metrics) for r in before)
    assert rows(metrics)[:2] == before


# ---- 2. a run holds its folder -----------------------------------------------------------------

def test_a_second_run_on_a_held_folder_stops_naming_it_and_a_killed_run_frees_it(
        data, tmp_path, capsys):
    out = tmp_path / "held"
    first = subprocess.Popen([sys.executable, "-m", "usplat_dr",
                              *usplat_train(*overrides(data, out, 100_000))],
                             env=environment(), stderr=subprocess.PIPE)
    leftover = out / "checkpoints" / ".last.ckpt.k1ll3d_x.tmp"
    try:
        started = wait_for(lambda: (out / "checkpoints" / "last.ckpt").exists(), first)
        assert started, stop(first)[-2000:]
        leftover.write_bytes(b"a killed write")  # the held folder's files are left alone
        status = main(usplat_train(*overrides(data, out, 1)))
        err = one_line_error(capsys, status)
        assert str(out) in err and f"pid {first.pid}" in err and "output_dir" in err
        assert leftover.exists()
        COUNTS["second run on a held folder refused"] += 1
    finally:
        stop(first)
    from usplat_dr.training.run_folder import run_folder_lock

    with run_folder_lock(out):  # SIGKILLed: no stale lock, and the leftover is removed
        assert not leftover.exists()


# ---- 3. temporary files of killed writes are removed at the next start -------------------------

def test_a_run_removes_the_temporary_files_killed_writes_left(data, run, tmp_path, capsys):
    leftovers = [run / ".metrics.csv.a1b2c3d4.tmp", run / "checkpoints" / ".last.ckpt.x_y9zz0q.tmp",
                 run / "validation" / "deep" / ".step_0000002.png.qwertyui.tmp"]
    # not a temporary file of the atomic writer, or not in the run folder: kept
    kept = [run / "notes.tmp", run / ".hidden", run / "checkpoints" / ".last.ckpt.tmp"]
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    kept.append(outside / ".data.abcdefgh.tmp")
    (run / "linked").symlink_to(outside, target_is_directory=True)  # not followed
    for path in leftovers + kept:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("x")
    assert main(usplat_train("--resume", *overrides(data, run, RUN_STEPS))) == 0, \
        capsys.readouterr()
    assert not any(p.exists() for p in leftovers)
    assert all(p.exists() for p in kept)


# ---- 4. a diverging run stops with its last good state -----------------------------------------

def test_parameters_gone_nan_stop_the_run_with_its_last_good_checkpoint(data, tmp_path,
                                                                        monkeypatch):
    original = Trainer.train_step

    def nan_at_step_2(self, batch):
        if self.step == 2:  # after the step-2 checkpoint: a parameter turns NaN
            next(self.model.parameters()).data.fill_(float("nan"))
        return original(self, batch)

    monkeypatch.setattr(Trainer, "train_step", nan_at_step_2)
    with pytest.raises(SystemExit) as stopped:
        main(usplat_train(*overrides(data, tmp_path, 6)))
    message = str(stopped.value.code)
    assert "\n" not in message and "non-finite" in message
    assert "last.ckpt (step 2)" in message and "--resume" in message
    _, step = load_model(tmp_path / "checkpoints" / "last.ckpt")  # refuses non-finite
    assert step == 2
    COUNTS["diverging runs stopped with their last good state"] += 1


def test_non_finite_forward_errors_are_skipped_then_stop_with_the_state_saved(data, tmp_path):
    trainer = Trainer(load_config(["synthetic_tiny.yaml"],
                                  overrides(data, tmp_path, 10, "train.max_nonfinite=2")))
    model, original = trainer.model, trainer.model.forward
    after_step_1 = {}

    def forward(*args, **kwargs):
        if trainer.step >= 1:  # what the rasteriser raises on NaN means
            after_step_1.update({k: v.clone() for k, v in model.state_dict().items()})
            raise ValueError("means must be finite, got NaN or Inf values")
        return original(*args, **kwargs)

    model.forward = forward
    with pytest.raises(TrainingStopped, match="2 steps in a row"):
        trainer.fit()
    assert trainer.skipped == 2
    saved = torch.load(trainer.checkpoint_path, weights_only=True)
    assert saved["step"] == 2  # saved when it stopped: the weights of the last good step
    assert all(torch.equal(saved["model"][k], v) for k, v in after_step_1.items())
    COUNTS["diverging runs stopped with their last good state"] += 1


def test_a_run_without_a_test_stage_validates_on_a_training_example(tmp_path):
    # the validation grid of the last step falls back to a training example, named by its
    # scene (it used to end the run with a KeyError after the last checkpoint)
    root = tmp_path / "data"
    write_plain_dataset(root, "train", [[fake_scene("only", 10, shape=(32, 32), fmt="png")]])
    trainer = Trainer(load_config(["synthetic_tiny.yaml"], overrides(root, tmp_path / "r", 1)))
    assert trainer.fit()["step"] == 1
    assert (tmp_path / "r" / "validation" / "step_0000001_only.png").is_file()


# ---- 5. everyday mistakes: one line, status 2 --------------------------------------------------

@pytest.mark.parametrize("change", ["model.variant=full", "model.preset=small"])
def test_resuming_another_model_names_the_setting(data, run, capsys, change):
    key, now = change.split("=")
    was = {"model.variant": "baseline", "model.preset": "tiny"}[key]
    err = one_line_error(capsys, main(usplat_train("--resume", *overrides(data, run, RUN_STEPS),
                                                   change)))
    assert f"{key}={was}" in err and f"{key}={now}" in err and "last.ckpt" in err


def test_resuming_with_another_schedule_names_the_settings(data, run, capsys):
    # before: the schedule, sized for RUN_STEPS, raised torch's "Tried to step N times" one
    # step past the run's end, and the steps since the last checkpoint were lost
    err = one_line_error(capsys, main(usplat_train("--resume", *overrides(data, run, 2000))))
    assert f"train.steps={RUN_STEPS} (this run: 2000)" in err and f"pass train.steps={RUN_STEPS}" \
        in err


def truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def drop_optimizer(path: Path) -> None:
    state = torch.load(path, weights_only=True)
    del state["optimizer"]
    torch.save(state, path)


def float8_weight(path: Path) -> None:
    # a weight of the right shape in a dtype load_state_dict would cast silently
    state = torch.load(path, weights_only=True)
    name = next(k for k, v in state["model"].items() if v.is_floating_point())
    state["model"][name] = state["model"][name].to(torch.float8_e4m3fn)
    torch.save(state, path)


@pytest.mark.parametrize("damage", [truncate, drop_optimizer, float8_weight])
def test_a_damaged_checkpoint_names_the_file_and_the_fix(data, run, capsys, damage):
    damage(run / "checkpoints" / "last.ckpt")
    err = one_line_error(capsys, main(usplat_train("--resume", *overrides(data, run, RUN_STEPS))))
    assert "last.ckpt" in err and "move it away" in err
    if damage is float8_weight:
        assert "float8_e4m3fn" in err


def test_a_damaged_random_state_names_the_file_and_the_fix(data, run, capsys):
    path = run / "checkpoints" / "last.ckpt"
    state = torch.load(path, weights_only=True)
    state["rng"]["torch"] = torch.zeros(3, dtype=torch.uint8)  # 3 bytes, not a generator's
    torch.save(state, path)
    err = one_line_error(capsys, main(usplat_train("--resume", *overrides(data, run, RUN_STEPS))))
    assert "last.ckpt holds a damaged random state" in err and "move it away" in err


def test_a_damaged_metrics_file_is_kept_aside_and_the_run_goes_on(data, run, capsys):
    (run / "metrics.csv").write_bytes(b"\x00\xff not a csv,,,\n1,2\n")
    assert main(usplat_train("--resume", *overrides(data, run, RUN_STEPS))) == 0, \
        capsys.readouterr()
    assert (run / "metrics.csv.damaged").read_bytes().startswith(b"\x00\xff")
    assert [r["step"] for r in rows(run / "metrics.csv")] == [str(s) for s in
                                                                range(3, RUN_STEPS + 1)]


def test_a_training_set_that_shrank_under_a_resumed_run(run, tmp_path, capsys):
    # the checkpoint took 2 batches of epoch 0; the set now has 1 scene (1 batch an epoch)
    smaller = write_data(tmp_path / "smaller", scenes=1)
    err = one_line_error(capsys, main(usplat_train("--resume", *overrides(smaller, run, 4))))
    assert "epoch 0" in err and "dataset.roots" in err and "last.ckpt" in err


@pytest.mark.parametrize("value, named", [
    ("threads=100000", f"os.cpu_count() = {os.cpu_count()}"),
    ("dataset.view_sampler.num_target_views=0", "num_target_views=0"),
    ("dataset.view_sampler.num_target_views=-2", "num_target_views=-2"),
    ("dataset.view_sampler.min_distance_between_context_views=7", "<= max_distance"),
    ("dataset.view_sampler.initial_min_distance_between_context_views=-1", "must be >= 0"),
    ("dataset.view_sampler.min_distance_to_context_views=-1", "must be >= 0"),
    ("dataset.view_sampler.max_distance_beyond_context_views=-3", "must be >= 0"),
    ("dataset.view_sampler.warm_up_steps=-5", "warm_up_steps=-5"),
    ("keep_cores_awake=sometimes", "true, false or auto"),
])
def test_out_of_range_values_stop_before_training(data, tmp_path, capsys, monkeypatch, value,
                                                  named):
    def accepted(*args, **kwargs):
        pytest.fail(f"{value} was accepted")  # (100000 threads would start them all)

    monkeypatch.setattr("usplat_dr.jobs.train.train", accepted)
    err = one_line_error(capsys, main(usplat_train(*overrides(data, tmp_path, 1), value)))
    assert value.split("=")[0] in err and named in err and "command line" in err


def test_an_output_dir_that_is_a_file(data, tmp_path, capsys):
    path = tmp_path / "a_file"
    path.write_text("not a folder")
    err = one_line_error(capsys, main(usplat_train(*overrides(data, path, 1))))
    assert f"output_dir={path}" in err and "existing file" in err
    assert path.read_text() == "not a folder"


def disk_full(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


@pytest.mark.parametrize("writer, file", [("trainer.torch_save", "last.ckpt"),
                                          ("run_log.atomic_open", "metrics.csv")])
def test_a_full_disk_names_the_file(data, tmp_path, capsys, monkeypatch, writer, file):
    monkeypatch.setattr(f"usplat_dr.training.{writer}", disk_full)
    err = one_line_error(capsys, main(usplat_train(*overrides(data, tmp_path, 2))))
    assert "disk full" in err and str(tmp_path) in err and file in err


def test_a_file_size_limit_stops_a_real_run_in_one_line_and_loses_nothing(data, tmp_path):
    """A real process under ``ulimit -f`` (the kernel refuses writes past 256 KiB with EFBIG,
    SIGXFSZ ignored as batch schedulers do): the first checkpoint (~2 MB for the tiny
    (a)) cannot be written; the run stops with one line naming it, exit 2, and leaves no
    temporary file."""
    import resource

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (256 * 1024, 256 * 1024))

    out = tmp_path / "limited"
    proc = subprocess.run([sys.executable, "-m", "usplat_dr",
                           *usplat_train(*overrides(data, out, 2))], env=environment(),
                          preexec_fn=limit, capture_output=True, timeout=600, check=False)
    err = proc.stderr.decode().strip()
    assert proc.returncode == 2, err[-2000:]
    assert err.count("\n") == 0 and "disk full" in err and "last.ckpt" in err, err
    assert not list(out.rglob("*.tmp")) and not (out / "checkpoints" / "last.ckpt").exists()
    COUNTS["a real file-size limit: one line, no temporary file"] += 1


# ---- 6. a path stored in a checkpoint is never opened ------------------------------------------

@pytest.mark.parametrize("kind", ["file", "fifo"])
def test_loading_a_checkpoint_never_opens_its_resnet_weights_path(tmp_path, monkeypatch, kind):
    from usplat_dr.model import UniqueSplat

    model = UniqueSplat.from_preset("tiny", variant="full")  # the variant with a ResNet18
    weights = tmp_path / "resnet18.pth"
    if kind == "file":
        weights.write_bytes(b"not a weight file")  # torch.load would fail on it
    else:
        os.mkfifo(weights)  # opening it would block
    path = tmp_path / "k.ckpt"
    torch.save({"model": model.state_dict(), "step": 3,
                "model_config": {**model.cfg.to_dict(), "resnet_weights": str(weights)}}, path)
    load = torch.load

    def guarded(f, *args, **kwargs):
        assert str(f) != str(weights), "the checkpoint's resnet_weights was opened"
        return load(f, *args, **kwargs)

    monkeypatch.setattr(torch, "load", guarded)
    loaded, step = load_model(path)
    assert step == 3 and loaded.cfg.resnet_weights is None
    expected = model.state_dict()
    assert all(torch.equal(v, expected[k]) for k, v in loaded.state_dict().items())


def test_zz_the_counts(capsys):
    """Prints what the tests above saw (``pytest tests/training/test_run_safety.py -q``)."""
    assert COUNTS["metrics rows lost"] == 0
    with capsys.disabled():
        print("\nprocess faults: " + ", ".join(f"{n} {k}" for k, n in sorted(COUNTS.items())))
