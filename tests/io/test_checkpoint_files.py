"""Checkpoints are read without running their code: a file carrying a pickled callable is
refused with a clear error by every loader and by the CLI, and nothing executes; full
unpickling only behind an explicit opt-in."""

import os

import pytest
import torch

from usplat_dr.cli import main
from usplat_dr.io import UntrustedCheckpointError, load_torch_file
from usplat_dr.model import UniqueSplat
from usplat_dr.training.checkpoints import init_from_checkpoint, load_model


class Payload:
    """Unpickling this calls ``os.mkdir(marker)``: proof that code ran."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.mkdir, (self.marker,))


@pytest.fixture
def evil(tmp_path):
    """A usplat-looking checkpoint whose config carries the payload."""
    model = UniqueSplat.from_preset("tiny", variant="baseline")
    marker = tmp_path / "code_ran"
    path = tmp_path / "evil.ckpt"
    torch.save({"model": model.state_dict(), "model_config": model.cfg.to_dict(), "step": 1,
                "config": {"dataset": {"image_shape": [32, 32]}, "x": Payload(marker)}}, path)
    assert not marker.exists()
    return path, marker


def test_loaders_refuse_pickled_code_and_run_nothing(evil):
    path, marker = evil
    with pytest.raises(UntrustedCheckpointError, match="posix.mkdir|os.mkdir"):
        load_torch_file(path)
    with pytest.raises(UntrustedCheckpointError, match="--trust-checkpoint"):
        load_model(path)
    model = UniqueSplat.from_preset("tiny", variant="full")
    with pytest.raises(UntrustedCheckpointError):
        init_from_checkpoint(model, path)
    with pytest.raises(UntrustedCheckpointError):
        model.load_mvsplat(str(path))
    assert not marker.exists()
    # the opt-in unpickles fully (and so runs the payload: only for files you trust)
    load_torch_file(path, trust=True)
    assert marker.is_dir()


@pytest.mark.parametrize("command", ["eval", "render", "export-ply"])
def test_cli_refuses_pickled_code_with_one_line(evil, tmp_path, command, capsys):
    path, marker = evil
    index = "standard=x.json" if command == "eval" else "x.json"  # never read: refused first
    assert main(["-q", command, "--checkpoint", str(path), "--data", str(tmp_path), "--index",
                 index]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"usplat {command}: error: checkpoint") and "\n" not in err
    assert "refused" in err and "--trust-checkpoint" in err
    assert not marker.exists()


def test_unreadable_files_name_the_file(tmp_path):
    (tmp_path / "text.ckpt").write_text('{"not": "a torch file"}')
    with pytest.raises(ValueError, match="text.ckpt.*not a file written by torch.save"):
        load_torch_file(tmp_path / "text.ckpt")
    torch.save({"a": torch.zeros(1000)}, tmp_path / "full.ckpt")
    (tmp_path / "cut.ckpt").write_bytes((tmp_path / "full.ckpt").read_bytes()[:500])
    with pytest.raises(ValueError, match="cut.ckpt.*torch.save"):
        load_torch_file(tmp_path / "cut.ckpt")
    with pytest.raises(FileNotFoundError, match="missing.ckpt"):
        load_torch_file(tmp_path / "missing.ckpt")
