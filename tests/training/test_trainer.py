"""Training: overfitting one scene, exact resume, stopping on signals and on non-finite steps,
distributed data parallel (2 gloo ranks) against one process on the combined batch, configs."""

import csv
import dataclasses
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.synth_sets import tiny_training_config
from usplat_dr.config import ConfigError, load_config
from usplat_dr.data.dataset import dataset_from_section
from usplat_dr.data.types import model_inputs
from usplat_dr.evaluation.lpips import LPIPSWeightsMissing
from usplat_dr.model.budget import GaussianBudget
from usplat_dr.training import Trainer, TrainingStopped
from usplat_dr.training.checkpoints import export_weights, training_depth_range
from usplat_dr.training.config import RootCfg
from usplat_dr.training.optim import GRAD_GROUPS, clip_gradients, group_grad_norms

CONFIGS = Path(__file__).parents[2] / "usplat_dr" / "configs"
pytestmark = pytest.mark.usefixtures("restore_threads")


def config(root: Path, out: Path, steps: int, *overrides: str) -> dict:
    return tiny_training_config(CONFIGS / "synthetic_tiny.yaml", root, out, steps,
                                "dataset.view_sampler.min_distance_between_context_views=3",
                                "dataset.view_sampler.initial_min_distance_between_context_"
                                "views=3", *overrides)


def params(model) -> dict:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def test_config_composition_and_errors(tmp_path):
    cfg = load_config([CONFIGS / "finetune_mvsplat.yaml"], ["optimizer.lr=3e-6",
                                                             "train.steps=10"])
    assert cfg["optimizer"]["lr"] == 3e-6 and cfg["optimizer"].get("gradient_clip") is None
    assert cfg["model"] == {"preset": "paper", "variant": "full",
                            "init_mvsplat": "checkpoints/re10k.ckpt"}
    assert cfg["dataset"]["name"] == "re10k" and cfg["train"]["steps"] == 10
    with pytest.raises(ConfigError, match="must look like"):
        load_config([CONFIGS / "base.yaml"], ["optimizer.lr"])
    with pytest.raises(ConfigError, match="does not exist"):
        load_config([tmp_path / "none.yaml"])
    (tmp_path / "a.yaml").write_text("include: [a.yaml]\n")
    with pytest.raises(ConfigError, match="includes itself"):
        load_config([tmp_path / "a.yaml"])
    # packaged configs by name; a user's file includes a file beside it or a packaged name
    assert load_config(["synthetic_tiny.yaml"]) == load_config([CONFIGS / "synthetic_tiny.yaml"])
    (tmp_path / "mine.yaml").write_text("include: [synthetic_tiny.yaml, b.yaml]\nseed: 3\n")
    (tmp_path / "b.yaml").write_text("train: {steps: 7}\n")
    mine = load_config([tmp_path / "mine.yaml"])
    assert mine["seed"] == 3 and mine["train"]["steps"] == 7
    assert mine["model"]["preset"] == "tiny"  # from the packaged model/tiny.yaml
    with pytest.raises(ConfigError, match=r"not a packaged config.*synthetic_tiny_depth\.yaml"):
        load_config(["train/configs/synthetic_tiny.yaml"])  # the old location


def test_typed_config_has_one_source_of_defaults_and_names_bad_keys(tmp_path):
    assert load_config(["base.yaml"]) == {}  # it documents the recipe and sets nothing
    assert RootCfg.load({}) == RootCfg()  # the recipe: the dataclasses' defaults only
    recipe = RootCfg()
    assert (recipe.train.steps, recipe.train.checkpoint_every, recipe.train.validate_every) == (
        300_000, 1000, 5000)
    assert (recipe.optimizer.lr, recipe.optimizer.gradient_clip, recipe.loss.lpips,
            recipe.loss.lpips_after_step, recipe.optimizer.hyper_lr_scale) == (
        2e-4, 0.5, 0.05, 150_000, 1.0)
    typed = RootCfg.load(load_config(["finetune_mvsplat.yaml"], ["train.steps=10"]))
    assert typed.train.steps == 10 and typed.optimizer.lr == 1e-6
    assert typed.train.validate_every == 5000 and typed.model.variant == "full"
    assert isinstance(RootCfg.load({"optimizer": {"lr": 1}}).optimizer.lr, float)
    (tmp_path / "mine.yaml").write_text("include: [synthetic_tiny.yaml]\ntrain: {stepz: 3}\n")
    with pytest.raises(ConfigError, match=r"unknown key 'train\.stepz' \(set in .*mine\.yaml"):
        RootCfg.load(load_config([tmp_path / "mine.yaml"]))
    with pytest.raises(ConfigError, match=r"train\.steps='abc': expected int.*"
                                          r"command line \(train\.steps=abc\)"):
        RootCfg.load(load_config(["synthetic_tiny.yaml"], ["train.steps=abc"]))
    with pytest.raises(ConfigError, match=r"unknown key 'learning_rate'.*command line"):
        RootCfg.load(load_config(["synthetic_tiny.yaml"], ["learning_rate=1"]))
    with pytest.raises(ConfigError, match=r"loss\.depth=True: expected float"):
        RootCfg.load({"loss": {"depth": True}})


def test_bad_sections_and_missing_lpips_files_stop_at_start(trainer_set, tmp_path):
    with pytest.raises(ConfigError, match="unknown key"):
        Trainer(config(trainer_set, tmp_path, 2, "optimizer.learning_rate=1"))
    with pytest.raises(LPIPSWeightsMissing, match="vgg16-397923af.pth"):
        Trainer(config(trainer_set, tmp_path, 2, "loss.lpips=0.05", "loss.lpips_after_step=0"))
    with pytest.raises(ConfigError, match="dataset.roots"):
        Trainer(config(trainer_set, tmp_path, 2, "dataset.roots=[]"))


def test_overfitting_one_scene_raises_psnr(trainer_set, tmp_path, device):
    # On every available device (CPU always, CUDA where present: config ``device``).
    torch.manual_seed(0)
    trainer = Trainer(config(trainer_set, tmp_path, 120, "optimizer.lr=1e-3",
                             "optimizer.warm_up_fraction=0.05", f"device={device.type}"))
    batch = trainer.batches.next()

    def target_psnr():
        trainer.model.eval()
        with torch.no_grad():
            out = trainer.model(*model_inputs(batch, trainer.device))
        mse = (out.color.clamp(0, 1).cpu() - batch["target"]["image"]).square().mean()
        return (-10 * torch.log10(mse)).item()

    before = target_psnr()
    for _ in range(120):  # the same scene and views every step
        trainer.train_step(batch)
    after = target_psnr()
    # Measured: 9.6 -> 25.8 dB (random init renders a nearly black image); 8 dB leaves
    # headroom for other BLAS builds and thread counts, far above what noise could give.
    assert after > before + 8, (before, after)


def test_resume_continues_exactly(trainer_set, tmp_path):
    # One thread: the float sums (torch's and the rasteriser's scatter-adds) then run in a
    # fixed order, so "exactly" can be bit for bit. (With 2 threads, two straight runs differ
    # by ~1e-5 in the weights after 6 Adam steps: accumulation order, amplified by Adam.)
    opts = ("train.checkpoint_every=3", "train.log_every=1", "threads=1")
    straight = Trainer(config(trainer_set, tmp_path / "a", 6, *opts))
    straight.fit()
    first = Trainer(config(trainer_set, tmp_path / "b", 6, *opts))
    # a run killed right after its step-3 checkpoint (its scheduler still planned 6 steps)
    first.config = dataclasses.replace(first.config,
                                       train=dataclasses.replace(first.config.train, steps=3))
    first.fit()
    # the checkpoint is tensors and plain data (RNG states included): weights_only loads it
    state = torch.load(tmp_path / "b" / "checkpoints" / "last.ckpt", weights_only=True)
    assert state["step"] == 3 and isinstance(state["rng"]["numpy"], dict)
    resumed = Trainer(config(trainer_set, tmp_path / "b", 6, *opts))
    assert resumed.resume() and resumed.step == 3
    resumed.fit()
    a, b = params(straight.model), params(resumed.model)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert torch.equal(straight.optimizer.state_dict()["state"][0]["exp_avg"],
                       resumed.optimizer.state_dict()["state"][0]["exp_avg"])
    # the metrics log of the resumed run is the straight run's, step for step
    import csv

    def losses(run):
        with open(tmp_path / run / "metrics.csv") as f:
            return [(int(r["step"]), float(r["loss"])) for r in csv.DictReader(f)]

    a_rows, b_rows = losses("a"), losses("b")
    assert [s for s, _ in b_rows] == [1, 2, 3, 4, 5, 6]
    assert a_rows == b_rows


def test_the_depth_range_trained_on_is_recorded_resumed_and_shipped(trainer_set, tmp_path):
    # the scenes' own near_far records (read from the chunk files, not through the trainer)
    scenes = [s for f in sorted(trainer_set.glob("train/*.torch"))
              for s in torch.load(f, weights_only=True)]
    near = [float(s["near_far"][0]) for s in scenes]
    far = [float(s["near_far"][1]) for s in scenes]
    opts = ("train.checkpoint_every=2", "threads=1")
    first = Trainer(config(trainer_set, tmp_path / "run", 2, *opts))
    first.fit()
    recorded = first.depth_range
    # what the batches drew lies within the set's scenes, as float32 values of them (recorded
    # as the shortest decimals naming those float32 values: compared as float32)
    f32 = [float(np.float32(v)) for v in recorded]
    assert float(np.float32(min(near))) <= f32[0] <= f32[1] <= float(np.float32(max(near))), (
        recorded, near)
    assert float(np.float32(min(far))) <= f32[2] <= f32[3] <= float(np.float32(max(far))), (
        recorded, far)
    checkpoint = tmp_path / "run" / "checkpoints" / "last.ckpt"
    assert torch.load(checkpoint, weights_only=True)["depth_range"] == recorded
    resumed = Trainer(config(trainer_set, tmp_path / "run", 2, *opts))
    assert resumed.resume() and resumed.depth_range == recorded
    shipped = export_weights(checkpoint, tmp_path / "shipped.pt")
    assert training_depth_range(shipped) == recorded


def test_signal_saves_and_stops(trainer_set, tmp_path):
    trainer = Trainer(config(trainer_set, tmp_path, 50))
    original = trainer.train_step

    def step_then_signal(batch):
        out = original(batch)
        if trainer.step == 1:
            trainer._on_signal(15, None)  # what SIGTERM triggers
        return out

    trainer.train_step = step_then_signal
    result = trainer.fit()
    assert result["step"] == 2 and trainer.checkpoint_path.is_file()
    again = Trainer(config(trainer_set, tmp_path, 50))
    assert again.resume() and again.step == 2


def test_non_finite_steps_are_skipped_then_stop(trainer_set, tmp_path):
    trainer = Trainer(config(trainer_set, tmp_path, 20, "train.max_nonfinite=3"))
    before = params(trainer.model)
    original = trainer.loss

    def nan_loss(out, target):
        loss, parts = original(out, target)
        return loss * float("nan"), parts

    trainer.loss = nan_loss
    with pytest.raises(TrainingStopped, match="3 steps in a row"):
        trainer.fit()
    assert trainer.skipped == 3 and trainer.checkpoint_path.is_file()
    after = params(trainer.model)
    assert all(torch.equal(before[k], after[k]) for k in before)  # no update was applied


def test_distributed_two_ranks_equal_one_process_on_the_combined_batch(trainer_set, tmp_path):
    # Rank r trains on example r; one process trains on both at once. DDP averages the
    # ranks' gradients = the gradient of the mean loss over the combined batch.
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[2])}  # imports tests.*
    worker = Path(__file__).parent / "ddp_worker.py"
    subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone",
                    "--nproc_per_node", "2", str(worker), str(trainer_set), str(tmp_path)],
                   check=True, env=env, timeout=300)
    # The one-process reference runs in a fresh process too: this process may have set up
    # oneDNN for another ISA (an in-process `usplat` command pins AVX2; measured: AVX2 vs
    # AVX-512 convolutions alone move these gradients by 1.4e-3 relative).
    subprocess.run([sys.executable, str(worker), str(trainer_set), str(tmp_path), "single"],
                   check=True, env=env, timeout=300)
    ddp = torch.load(tmp_path / "ddp.pt")
    single = torch.load(tmp_path / "single.pt")["grads"]
    # The update is the clipped gradient (compared here) fed to Adam. Adam's first step is
    # about lr * sign(g) for every non-zero g, so weights would amplify float32 noise in
    # near-zero gradients to a whole step; the gradients themselves are the sharp test.
    assert set(single) == set(ddp["grads"])
    flat_s = torch.cat([g.flatten() for g in single.values()])
    flat_d = torch.cat([ddp["grads"][n].flatten() for n in single])
    # batched vs per-example sums in float32: ~1e-6 relative (5e-7 measured); 1e-4 leaves
    # room, while one rank's example alone (no averaging) is off by 48% (measured).
    rel = ((flat_s - flat_d).norm() / flat_s.norm()).item()
    assert rel < 1e-4, rel
    assert flat_s.norm() > 0


def first_examples(trainer, n):
    # the whole validation set in its fixed order, whatever the process's rank
    ds = dataset_from_section(trainer.cfg["dataset"], "val", rank=0, world_size=1)
    out = []
    for ex in ds:
        out.append(ex)
        if len(out) == n:
            return out
    raise AssertionError("too few examples")


def test_usplat_train_writes_checkpoint_metrics_and_validation_grid(trainer_set, tmp_path):
    from usplat_dr.cli import main

    overrides = [f"dataset.roots=[{trainer_set}]", "dataset.image_shape=[32,32]",
                 f"output_dir={tmp_path}", "train.steps=2", "train.validate_every=2",
                 "train.progress=false", "dataset.view_sampler.num_target_views=2",
                 "dataset.view_sampler.min_distance_between_context_views=3",
                 "dataset.view_sampler.initial_min_distance_between_context_views=3",
                 "dataset.view_sampler.max_distance_between_context_views=6",
                 "dataset.view_sampler.initial_max_distance_between_context_views=6"]
    assert main(["-q", "train", "--config", str(CONFIGS / "synthetic_tiny.yaml"),
                 *overrides]) == 0
    assert (tmp_path / "checkpoints" / "last.ckpt").is_file()
    assert len(list((tmp_path / "validation").glob("step_0000002_*.png"))) == 1
    rows = (tmp_path / "metrics.csv").read_text().splitlines()
    assert rows[0].startswith("step,loss") and rows[-1].startswith("2,")


def test_hyper_lr_scale_gives_the_hypernetwork_branches_their_own_rate(trainer_set, tmp_path):
    from usplat_dr.training.optim import parameter_groups

    trainer = Trainer(config(trainer_set, tmp_path / "h", 4, "model.variant=full",
                             "optimizer.hyper_lr_scale=10", "threads=1"))
    primary, hyper = trainer.optimizer.param_groups
    names = {id(p): n for n, p in trainer.model.named_parameters()}
    assert all(names[id(p)].startswith("primary.") for p in primary["params"])
    assert not any(names[id(p)].startswith("primary.") for p in hyper["params"])
    assert len(primary["params"]) + len(hyper["params"]) == len(names)
    for _ in range(3):  # the one-cycle schedule keeps the ratio at every step
        assert hyper["lr"] == pytest.approx(10 * primary["lr"], rel=1e-12)
        trainer.optimizer.step()  # no gradients: changes nothing, keeps torch's order check quiet
        trainer.scheduler.step()
    # scale 1 (the default) or a model without hypernetworks: Adam's single group
    assert len(parameter_groups(trainer.model, 1e-3)) == 1
    with pytest.raises(ConfigError, match="hyper_lr_scale"):
        parameter_groups(trainer.model, 1e-3, 0)


def test_a_skipped_step_advances_the_learning_rate_schedule(trainer_set, tmp_path):
    # Decided: the learning rate is a function of the step counter. A skipped (non-finite)
    # step consumes its batch and its step, so the schedule advances with it; the rates of
    # the following steps are those of a run without the skip (compared exactly: the same
    # scheduler arithmetic on the same step count).
    opts = ("train.log_every=1", "threads=1")
    clean = Trainer(config(trainer_set, tmp_path / "a", 4, *opts))
    clean.fit()
    skipping = Trainer(config(trainer_set, tmp_path / "b", 4, *opts))
    original = skipping.loss

    def nan_at_step_1(out, batch):
        loss, parts = original(out, batch)
        return (loss * float("nan") if skipping.step == 1 else loss), parts

    skipping.loss = nan_at_step_1
    skipping.fit()
    assert skipping.skipped == 1
    assert skipping.scheduler.get_last_lr() == clean.scheduler.get_last_lr()
    assert skipping.scheduler.last_epoch == clean.scheduler.last_epoch == 4

    def lrs(folder):
        with open(folder / "metrics.csv") as f:
            return {int(r["step"]): float(r["lr"]) for r in csv.DictReader(f)}

    a, b = lrs(tmp_path / "a"), lrs(tmp_path / "b")
    assert a[3] == b[3] and a[4] == b[4]


def test_lpips_joins_the_loss_at_its_step(trainer_set, tmp_path):
    # The LPIPS training branch with weight files of the real layouts (random values): the
    # term is logged from loss.lpips_after_step on, and it changes the update.
    from tests.evaluation.test_lpips import weight_files

    vgg, lin, *_ = weight_files(tmp_path)
    opts = ("train.log_every=1", "threads=1", "loss.lpips_after_step=1")
    with_lpips = Trainer(config(trainer_set, tmp_path / "a", 2, *opts, "loss.lpips=0.5",
                                f"loss.lpips_vgg={vgg}", f"loss.lpips_lin={lin}"))
    with_lpips.fit()
    without = Trainer(config(trainer_set, tmp_path / "b", 2, *opts, "loss.lpips=0"))
    without.fit()
    with open(tmp_path / "a" / "metrics.csv") as f:
        rows = {int(r["step"]): r for r in csv.DictReader(f)}
    assert rows[1]["lpips"] == "" and float(rows[2]["lpips"]) > 0
    a, b = params(with_lpips.model), params(without.model)
    assert any(not torch.equal(a[k], b[k]) for k in a)  # the LPIPS gradient moved weights


@pytest.mark.parametrize("setting", ["true", "false"])
def test_fit_keeps_the_cores_awake_only_while_it_trains(trainer_set, tmp_path, monkeypatch,
                                                        setting, caplog):
    from usplat_dr.training import cores as _cores

    seen = []

    class Recording(_cores.CoreKeeper):
        def start(self):
            super().start()
            seen.append(("start", len(self.procs)))
            return self

        def stop(self):
            seen.append(("stop", len(self.procs)))
            super().stop()

    monkeypatch.setattr(_cores, "CoreKeeper", Recording)
    trainer = Trainer(config(trainer_set, tmp_path, 1, f"keep_cores_awake={setting}",
                             "threads=1"))
    with caplog.at_level(logging.INFO, logger="usplat_dr.training.run_folder"):
        trainer.fit()
    on = "on" if setting == "true" else "off"
    assert f"core keeper {on}: keep_cores_awake={setting}" in caplog.messages
    if setting == "false":
        assert seen == []
    else:  # started with one spinner per core (on Linux), stopped when fit returned
        cpus = len(_cores.available_cpus()) if sys.platform.startswith("linux") else 0
        assert seen == [("start", cpus), ("stop", cpus)]


@pytest.mark.parametrize("clip", [1e-3, 1e6])  # clipping scales the gradients / leaves them
def test_clip_gradients_equals_group_norms_then_clip_grad_norm(trainer_set, tmp_path, clip):
    # The one-pass clip against the two calls it replaces, on the full variant with an
    # importance head in a budgeted step (all five gradient groups): the same norms and the
    # same clipped gradients, compared exactly (the same per-parameter norms, stacked and
    # reduced in the same order).
    trainer = Trainer(config(trainer_set, tmp_path / "c", 1, "model.variant=full",
                             "model.overrides.importance=true", "threads=1",
                             f"optimizer.gradient_clip={clip}"))
    batch = trainer.batches.next()
    out = trainer.model(*model_inputs(batch, trainer.device), global_step=0,
                        budget=GaussianBudget(0.3, tau=0.5))
    trainer.loss(out, batch)[0].backward()
    grads = {n: p.grad.clone() for n, p in trainer.model.named_parameters()
             if p.grad is not None}
    norm, parts = clip_gradients(trainer.model, clip)
    clipped = {n: p.grad.clone() for n, p in trainer.model.named_parameters()
               if p.grad is not None}
    for n, p in trainer.model.named_parameters():
        if p.grad is not None:
            p.grad.copy_(grads[n])
    expected_parts = group_grad_norms(trainer.model)
    expected = torch.nn.utils.clip_grad_norm_(trainer.model.parameters(), clip)
    assert set(parts) == set(GRAD_GROUPS.values())
    assert parts == expected_parts
    assert torch.equal(norm, expected)
    for n, p in trainer.model.named_parameters():
        if p.grad is not None:
            assert torch.equal(clipped[n], p.grad), n
    scale = min(1.0, clip / (norm.item() + 1e-6))
    assert any(not torch.equal(clipped[n], grads[n]) for n in grads) == (scale < 1)
