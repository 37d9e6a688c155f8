"""Add-on checkpoints (``export_weights(..., base=)``): a model fine-tuned with most weights
frozen ships as the weights that differ from a shipped checkpoint, naming it by file and
sha256, and loads like a complete checkpoint wherever that base is found."""

import dataclasses
import hashlib
import logging
import shutil

import pytest
import torch

from usplat_dr.io import torch_save
from usplat_dr.model import UniqueSplat
from usplat_dr.training import checkpoints
from usplat_dr.training.checkpoints import (
    export_weights,
    init_from_checkpoint,
    load_model,
    read_usplat_checkpoint,
    shipped_checkpoints,
)
from usplat_dr.training.loader import load


@pytest.fixture(autouse=True)
def _quiet_resnet(caplog):
    caplog.set_level(logging.ERROR, logger="usplat_dr.model.hypernet.resnet")


@pytest.fixture
def budget_checkpoint(tmp_path):
    """A training checkpoint of the budget stage on the shipped tiny_full: its weights, plus an
    importance head set to random values (as training would leave it)."""
    base = load("tiny_full")
    model = UniqueSplat(dataclasses.replace(base.cfg, importance=True))
    init_from_checkpoint(model, "tiny_full")
    torch.manual_seed(0)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.startswith("importance."):
                p.copy_(torch.randn_like(p))
    path = tmp_path / "last.ckpt"
    torch_save({"model": model.state_dict(), "model_config": model.cfg.to_dict(),
                "config": {"model": {"init_from": "tiny_full"}}, "step": 7}, path)
    return path, model


def test_an_addon_holds_only_what_differs_and_loads_as_the_whole_model(budget_checkpoint,
                                                                       tmp_path):
    path, model = budget_checkpoint
    addon = export_weights(path, tmp_path / "tiny_full_budget.pt", base="tiny_full")
    stored = torch.load(addon, map_location="cpu", weights_only=True)
    assert stored["model"] and all(k.startswith("importance.") for k in stored["model"])
    base_file = shipped_checkpoints()["study/tiny_full"]
    assert stored["base"] == {"file": "tiny_full.pt", "sha256": hashlib.sha256(
        base_file.read_bytes()).hexdigest()}
    # kilobytes beside a copy of the model (the size budget of the shipped weights)
    assert addon.stat().st_size < base_file.stat().st_size / 20
    loaded, step = load_model(addon)
    assert step == 7 and loaded.cfg.importance
    expected = {k: v.half().float() for k, v in model.state_dict().items()}  # float16 storage
    got = loaded.state_dict()
    assert got.keys() == expected.keys()
    assert all(torch.equal(got[k], expected[k]) for k in got)
    # the base's own weights were float16 already: the add-on's model is the base bit for bit
    base = load("tiny_full").state_dict()
    assert all(torch.equal(got[k], base[k]) for k in base)


def test_the_base_beside_the_addon_comes_first_and_must_be_the_same_file(
        budget_checkpoint, tmp_path, monkeypatch):
    path, _ = budget_checkpoint
    folder = tmp_path / "elsewhere"
    folder.mkdir()
    addon = export_weights(path, folder / "tiny_full_budget.pt", base="tiny_full")
    complete = read_usplat_checkpoint(addon)["model"]  # the base from the shipped ones
    beside = folder / "tiny_full.pt"
    beside.write_bytes(shipped_checkpoints()["baseline-64"].read_bytes())  # another file
    with pytest.raises(ValueError, match="another file"):
        read_usplat_checkpoint(addon)
    # with no shipped checkpoints at all, the right file beside it is enough
    shutil.copyfile(shipped_checkpoints()["study/tiny_full"], beside)
    monkeypatch.setattr(checkpoints, "CHECKPOINTS", tmp_path / "none")
    again = read_usplat_checkpoint(addon)["model"]
    assert again.keys() == complete.keys()
    assert all(torch.equal(again[k], complete[k]) for k in again)
    beside.unlink()
    with pytest.raises(FileNotFoundError, match="beside it"):
        read_usplat_checkpoint(addon)


@pytest.mark.parametrize("base, error, match", [
    ({"file": "nowhere.pt", "sha256": "0" * 64}, FileNotFoundError, "beside it"),
    ({"file": "../tiny_full.pt", "sha256": "0" * 64}, ValueError, "not a .pt file name"),
    ({"file": "/etc/passwd", "sha256": "0" * 64}, ValueError, "not a .pt file name"),
    ("tiny_full.pt", ValueError, "'base' must be"),
])
def test_a_bad_base_is_a_clear_error(budget_checkpoint, tmp_path, base, error, match):
    path, _ = budget_checkpoint
    addon = export_weights(path, tmp_path / "addon.pt", base="tiny_full")
    state = torch.load(addon, map_location="cpu", weights_only=True)
    state["base"] = base
    torch_save(state, addon)
    with pytest.raises(error, match=match):
        read_usplat_checkpoint(addon)


def test_an_addon_with_another_branch_design_leaves_out_the_bases_unused_weights(tmp_path):
    """A (c) whose view-specific branch reads the primary network's features (no ResNet18)
    trained on tiny_full: the add-on names the base's ResNet weights as unused, and loads as
    exactly the whole model (no unexpected keys)."""
    base = load("tiny_full")
    model = UniqueSplat(dataclasses.replace(base.cfg, view_features="primary"))
    shared = {k: v for k, v in base.state_dict().items() if k in model.state_dict()
              and model.state_dict()[k].shape == v.shape}
    model.load_state_dict(shared, strict=False)
    path = tmp_path / "last.ckpt"
    torch_save({"model": model.state_dict(), "model_config": model.cfg.to_dict(),
                "config": {"model": {"init_from": "tiny_full"}}, "step": 3}, path)
    addon = export_weights(path, tmp_path / "live.pt", base="tiny_full")
    unused = torch.load(addon, map_location="cpu", weights_only=True)["base"]["unused"]
    assert unused == sorted(set(base.state_dict()) - set(model.state_dict()))
    assert any(".resnet." in k for k in unused)
    loaded, _ = load_model(addon)
    got, expected = loaded.state_dict(), model.state_dict()
    assert got.keys() == expected.keys()
    assert all(torch.equal(got[k], expected[k].half().float()) for k in got)
