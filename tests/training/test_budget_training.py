"""The budget stage (train.budget_fractions, docs/model.md): the budget of each step, the
config's checks, and a few-step run from a trained checkpoint that keeps the unbudgeted model
bit for bit, trains the importance head, and saves a checkpoint that loads."""

import dataclasses
import math
from pathlib import Path

import pytest
import torch
from torch.utils.data import default_collate

from tests.synth_sets import tiny_training_config
from usplat_dr.config import ConfigError
from usplat_dr.data.dataset import dataset_from_section
from usplat_dr.data.types import model_inputs
from usplat_dr.model.budget import GaussianBudget
from usplat_dr.training import Trainer
from usplat_dr.training.checkpoints import load_model
from usplat_dr.training.config import RootCfg, model_from_config
from usplat_dr.training.losses import training_loss
from usplat_dr.training.stages import freeze_for_budget, step_budget

pytestmark = pytest.mark.usefixtures("restore_threads")


def config(root: Path, out: Path, steps: int, *overrides: str, name="synthetic_tiny_budget.yaml"):
    return tiny_training_config(name, root, out, steps, "train.log_every=1", "threads=1",
                                *overrides)


def test_each_step_draws_its_budget_from_the_config():
    choice = RootCfg(train=dataclasses.replace(RootCfg().train, steps=101,
                                               budget_fractions=(0.1, 0.3)))
    draws = [step_budget(choice, s) for s in range(101)]
    assert {d.keep for d in draws} == {0.1, 0.3}
    assert all(d.rank_by == "learned" for d in draws)
    # a function of (seed, step): the same again, on every rank and after a resume
    assert draws == [step_budget(choice, s) for s in range(101)]
    # tau geometric from 1.0 at the first step to 0.05 at the last
    assert draws[0].tau == 1.0 and math.isclose(draws[-1].tau, 0.05)
    assert math.isclose(draws[50].tau, math.sqrt(0.05))
    logu = RootCfg(train=dataclasses.replace(choice.train, budget_sampling="log_uniform",
                                             budget_fractions=(0.05, 0.6)))
    values = [step_budget(logu, s).keep for s in range(400)]
    assert 0.05 <= min(values) and max(values) <= 0.6
    # log-uniform: about half of the draws below the geometric mean sqrt(0.05 * 0.6)
    below = sum(v < math.sqrt(0.03) for v in values) / len(values)
    assert 0.4 < below < 0.6, below  # binomial(400, 0.5): 0.4..0.6 is 4 sigma
    assert step_budget(RootCfg(), 3) is None


def test_budget_settings_are_checked_and_name_the_key(trainer_set, tmp_path):
    with pytest.raises(ConfigError, match=r"train\.budget_fractions=\(0\.5, 1\.5\)"):
        RootCfg.load(config(trainer_set, tmp_path, 1, "train.budget_fractions=[0.5, 1.5]"))
    with pytest.raises(ConfigError, match="train.trainable='some'"):
        RootCfg.load(config(trainer_set, tmp_path, 1, "train.trainable=some"))
    no_head = RootCfg.load(config(trainer_set, tmp_path, 1, "model.overrides.importance=false"))
    with pytest.raises(ConfigError, match="model.overrides.importance=true"):
        freeze_for_budget(model_from_config(no_head.model), no_head)
    ones = RootCfg.load(config(trainer_set, tmp_path, 1, "train.budget_sampling=choice",
                               "train.budget_fractions=[0.1, 1.0]"))
    with pytest.raises(ConfigError, match="holds 1 with train.trainable=budget"):
        freeze_for_budget(model_from_config(ones.model), ones)


def test_budget_stage_from_a_trained_checkpoint(trainer_set, tmp_path):
    # (c) trained for a step, then the budget stage from it: every weight of (c) loaded, the
    # head new; only the head trains, so the unbudgeted model stays (c) bit for bit.
    base = Trainer(config(trainer_set, tmp_path / "c", 1, name="synthetic_tiny_depth.yaml"))
    base.fit()
    stage = Trainer(config(trainer_set, tmp_path / "budget", 4,
                           f"model.init_from={base.checkpoint_path}"))
    start = {k: v.clone() for k, v in stage.model.state_dict().items()}
    for k, v in base.model.state_dict().items():
        assert torch.equal(start[k], v), k
    assert any(k.startswith("importance.") for k in start)
    trainable = {n for n, p in stage.model.named_parameters() if p.requires_grad}
    assert trainable and all(n.startswith("importance.") for n in trainable)
    result = stage.fit()
    assert result["step"] == 4 and result["skipped"] == 0
    assert 0.05 <= result["budget"] <= 0.8 and math.isfinite(result["loss"])
    end = stage.model.state_dict()
    for k, v in start.items():
        if k.startswith("importance."):
            continue
        assert torch.equal(end[k], v), k  # frozen: bit for bit
    assert any(not torch.equal(end[k], start[k]) for k in start if k.startswith("importance."))
    rows = (tmp_path / "budget" / "metrics.csv").read_text().splitlines()
    assert "budget" in rows[0].split(",") and "grad_importance" in rows[0].split(",")
    # the checkpoint loads as a model with the head, and a budget keeps K per target
    model, step = load_model(stage.checkpoint_path)
    assert step == 4 and model.importance is not None
    batch = stage.batches.next()
    with torch.no_grad():
        out = model(*model_inputs(batch), budget=GaussianBudget(0.1))
        ref = base.model.eval()(*model_inputs(batch))
        same = model(*model_inputs(batch))
    assert (out.aux["kept"] == round(0.1 * 2 * 32 * 32)).all()
    assert torch.equal(same.color, ref.color)  # the unbudgeted render is (c)'s


def test_the_full_render_term_joins_a_budgeted_step(trainer_set, tmp_path):
    cfg = RootCfg.load(config(trainer_set, tmp_path, 1, "model.variant=baseline",
                              "train.trainable=all", "loss.full_render=1.0"))
    torch.manual_seed(0)
    model = model_from_config(cfg.model).train()
    example = next(iter(dataset_from_section(cfg.dataset, "train")))
    trainer_batch = default_collate([example])
    args = model_inputs(trainer_batch)
    out = model(*args, budget=GaussianBudget(0.2, tau=0.5))
    loss, parts = training_loss(out, trainer_batch, cfg.loss, 0, torch.device("cpu"))
    unbudgeted = model(*args)
    target = trainer_batch["target"]["image"]
    full = (unbudgeted.color - target).square().mean().item()
    # the same Gaussians rendered again: equal up to float32 summation order
    assert math.isclose(parts["full_mse"], full, rel_tol=1e-5)
    assert math.isclose(loss.item(), parts["mse"] + parts["full_mse"], rel_tol=1e-6)
