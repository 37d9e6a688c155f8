"""``usplat_dr.load``: one loader for every checkpoint users have (a shipped name, a training
checkpoint, an official MVSplat file), behind every command that takes ``--checkpoint``."""

import logging

import pytest
import torch

import usplat_dr
from usplat_dr.model import PrimaryNetwork, UniqueSplat
from usplat_dr.training import registry
from usplat_dr.training.checkpoints import (
    is_mvsplat_checkpoint,
    load_model,
    resolve_checkpoint,
    shipped_checkpoints,
    training_image_shape,
)
from usplat_dr.training.loader import load


def same_weights(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_a_shipped_name_and_its_file_load_the_same_model():
    path = shipped_checkpoints()["study/tiny_full"]
    by_name = usplat_dr.load("study/tiny_full")
    assert by_name.cfg.variant == "full" and not by_name.training
    assert same_weights(by_name, load(path))
    assert same_weights(by_name, load_model(path)[0])
    assert resolve_checkpoint("study/tiny_full.pt") == path
    assert training_image_shape("study/tiny_full") == (64, 64)


def test_an_old_name_loads_its_file_with_a_line_naming_the_new_one(caplog):
    registry._told.discard("tiny_full_beyond")
    with caplog.at_level(logging.WARNING, logger="usplat_dr.training.registry"):
        old = usplat_dr.load("tiny_full_beyond")
    assert "tiny_full_beyond is now full-64 (the same file)" in caplog.text
    assert same_weights(old, usplat_dr.load("full-64"))
    # no name: the shipped (c) for 64x64, whose branch acts
    assert same_weights(usplat_dr.load(), old)


def test_an_mvsplat_lightning_file_loads_as_the_paper_preset_baseline(tmp_path):
    torch.manual_seed(0)
    net = PrimaryNetwork()  # MVSplat's RE10K architecture, random weights
    lightning = {"state_dict": {f"encoder.{k}": v for k, v in net.state_dict().items()},
                 "epoch": 3, "global_step": 300000}
    path = tmp_path / "re10k.ckpt"
    torch.save(lightning, path)
    assert is_mvsplat_checkpoint(torch.load(path, weights_only=True))
    model = load(path)
    assert isinstance(model, UniqueSplat) and model.cfg.variant == "baseline"
    assert same_weights(model.primary, net)
    assert training_image_shape(path) is None  # MVSplat's files record none: 256x256 default


def test_a_name_that_is_no_file_lists_the_shipped_ones(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"shipped models \(usplat models; --all for "
                       r"study/ ones\): full-64, full-128, baseline-64"):
        load("tiny_fulll")
    with pytest.raises(FileNotFoundError, match="missing.ckpt' does not exist"):
        load(tmp_path / "missing.ckpt")
    stray = tmp_path / "stray.ckpt"
    torch.save({"weights": torch.zeros(2)}, stray)  # neither ours nor MVSplat's
    with pytest.raises(ValueError, match="not a usplat training checkpoint"):
        load(stray)
