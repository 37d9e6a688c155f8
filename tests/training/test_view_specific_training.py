"""The view-specific stage (train.trainable=view_specific, model.open_gate_std; docs/model.md,
"Is the branch live?"): from a trained (c), only the view-specific branch trains, the opened
gate gives it a gradient, and metrics.csv reads the view-specificity meter at validation."""

from pathlib import Path

import pytest
import torch

from tests.synth_sets import tiny_training_config
from usplat_dr.config import ConfigError
from usplat_dr.training import Trainer
from usplat_dr.training.config import RootCfg, model_from_config
from usplat_dr.training.run_log import read_metrics
from usplat_dr.training.stages import freeze_for_budget

pytestmark = pytest.mark.usefixtures("restore_threads")

BRANCH = ("view_embedding.", "specific.")


def config(root: Path, out: Path, steps: int, *overrides: str):
    return tiny_training_config("synthetic_tiny_depth.yaml", root, out, steps, "train.log_every=1",
                                "threads=1", *overrides)


def test_only_the_branch_trains_from_an_opened_gate_and_the_meter_is_logged(trainer_set,
                                                                            tmp_path):
    base = Trainer(config(trainer_set, tmp_path / "c", 1, "train.validate_every=100000"))
    base.fit()
    stage = Trainer(config(trainer_set, tmp_path / "vs", 3, "train.validate_every=3",
                           f"model.init_from={base.checkpoint_path}",
                           "train.trainable=view_specific", "model.open_gate_std=0.05",
                           "train.keep_every=2", "train.checkpoint_every=1"))
    start = {k: v.clone() for k, v in stage.model.state_dict().items()}
    loaded = base.model.state_dict()
    gate = "specific.hyper.net.4.weight"
    for k, v in loaded.items():
        if k != gate:  # every weight of (c) loaded as it was
            assert torch.equal(start[k], v), k
    assert not torch.equal(start[gate], loaded[gate])  # the opened gate: noise added
    trainable = {n for n, p in stage.model.named_parameters() if p.requires_grad}
    assert trainable and all(n.startswith(BRANCH) for n in trainable)
    assert any(n.startswith("view_embedding.features.resnet.") for n in trainable)
    stage.fit()
    end = stage.model.state_dict()
    for k, v in start.items():
        if not k.startswith(BRANCH):
            assert torch.equal(end[k], v), k  # primary network and H_a frozen: bit for bit
    # the opened gate passes a gradient to the ResNet, Proj and phi, so they move
    moved = [k for k in start if k.startswith("view_embedding.") and not torch.equal(
        end[k], start[k])]
    assert any(".resnet." in k for k in moved) and any(".phi." in k for k in moved)
    # train.keep_every=2: of the checkpoints at steps 1, 2, 3 the one at step 2 is kept
    kept = sorted(p.name for p in (tmp_path / "vs" / "checkpoints").glob("step_*.ckpt"))
    assert kept == ["step_0000002.ckpt"]
    rows = read_metrics(tmp_path / "vs")
    assert float(rows[-1]["grad_view_features"]) > 0
    # the meter at the validation step (the last) only, on the two targets of the scene:
    # with noise in U, Delta W differs between them
    assert [r["step"] for r in rows if r["view_spread"]] == ["3"]
    assert float(rows[-1]["view_spread"]) > 0
    assert float(rows[-1]["view_psnr_abs"]) > 0  # (and the renders differ by it)


def test_the_view_specific_stage_needs_the_branch(trainer_set, tmp_path):
    cfg = RootCfg.load(config(trainer_set, tmp_path, 1, "model.variant=agnostic",
                              "train.trainable=view_specific"))
    with pytest.raises(ConfigError, match="model.variant=full"):
        freeze_for_budget(model_from_config(cfg.model), cfg)
    cfg = RootCfg.load(config(trainer_set, tmp_path, 1, "model.variant=agnostic",
                              "model.open_gate_std=0.1"))
    with pytest.raises(ConfigError, match="open_gate_std"):
        model_from_config(cfg.model)
    with pytest.raises(ConfigError, match="model.open_gate_std=-1"):
        RootCfg.load(config(trainer_set, tmp_path, 1, "model.open_gate_std=-1"))
    with pytest.raises(ConfigError, match="train.keep_every=3 is not a multiple"):
        RootCfg.load(config(trainer_set, tmp_path, 1, "train.keep_every=3",
                            "train.checkpoint_every=2"))
