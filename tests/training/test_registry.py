"""The shipped models by name (usplat_dr.training.registry): the default of the commands is
the user (c) trained nearest the size asked, said; a name never changes size; old names load
with a line naming the new one; the shipped manifest holds what choosing needs."""

import json
import logging
import re
from argparse import Namespace

import numpy as np
import pytest
import torch

from usplat_dr.cli import main
from usplat_dr.data.chunks import stored_image_shape
from usplat_dr.jobs import arguments as job_arguments
from usplat_dr.training import registry
from usplat_dr.training.checkpoints import training_image_shape
from usplat_dr.training.registry import (
    canonical_name,
    default_checkpoint,
    resolve_checkpoint,
    shipped_models,
)


@pytest.fixture
def root(tmp_path):
    """A manifest of user (c)s trained at 64, 128 and 256 (``c-64``, ``c-128``, ``c-256``),
    a user (a) ``a-64`` that was ``old_a``, and a study model ``study/s``."""
    entries = []
    for name, variant, size, kind in (("c-64", "full", 64, "user"), ("c-128", "full", 128, "user"),
                                      ("c-256", "full", 256, "user"),
                                      ("a-64", "baseline", 64, "user"),
                                      ("study/s", "full", 64, "study")):
        stem = name.replace("/", "_")
        torch.save({"config": {"dataset": {"image_shape": [size, size]}}},
                   tmp_path / f"{stem}.pt")
        entries.append({"name": name, "file": f"{stem}.pt", "variant": variant, "kind": kind,
                        "training_shape": [size, size], "recipe": "r", "purpose": "p",
                        "old_names": ["old_a"] if name == "a-64" else [],
                        "sha256": "ab" * 32})
    (tmp_path / "manifest.json").write_text(json.dumps(entries))
    return tmp_path


@pytest.mark.parametrize("shape, expected", [
    ((64, 64), "c-64"), ((128, 128), "c-128"), ((100, 200), "c-128"),  # the shorter side: 100
    ((90, 90), "c-64"),  # 90: 0.49 octaves above 64, 0.51 below 128
    ((512, 512), "c-256"), ((16, 16), "c-64"), (None, "c-256")])  # own photographs: the largest
def test_the_default_is_the_user_c_trained_nearest_the_size_asked(root, shape, expected):
    name, line = default_checkpoint(shape, root=root)
    assert name == expected
    assert line.startswith(f"no --checkpoint: using {expected}, the shipped (c) trained at ")
    # the (a)s are never the default of the (c), and a study model never is
    assert default_checkpoint(shape, "baseline", root)[0] == "a-64"


def test_names_resolve_study_names_too_and_old_names_say_their_new_one(root, caplog):
    registry._told.discard("old_a")
    assert resolve_checkpoint("c-128", root) == root / "c-128.pt"
    assert resolve_checkpoint("study/s", root) == root / "study_s.pt"
    assert resolve_checkpoint("c-128.pt", root) == root / "c-128.pt"
    with caplog.at_level(logging.WARNING):
        assert resolve_checkpoint("old_a", root) == root / "a-64.pt"
        assert resolve_checkpoint("old_a", root) == root / "a-64.pt"
    said = [r.getMessage() for r in caplog.records if "old_a" in r.getMessage()]
    assert said == [("old_a is now a-64 (the same file); the old name loads for one more "
                    "release")]  # once per process
    assert canonical_name("nothing", root) is None
    with pytest.raises(FileNotFoundError, match="usplat models"):
        resolve_checkpoint("nothing", root)


def test_a_manifest_whose_names_choose_two_models_is_refused(root):
    entries = json.loads((root / "manifest.json").read_text())
    entries[1]["old_names"] = ["c-64"]  # c-128 once called c-64: two models for one name
    (root / "manifest.json").write_text(json.dumps(entries))
    with pytest.raises(ValueError, match="a name .or old name. given twice"):
        shipped_models(root)


def test_a_shipped_name_wins_over_a_file_of_that_name_here(root, tmp_path, monkeypatch,
                                                          caplog):
    # a file ./c-64 in the current folder (garbage or another model) is not what the name
    # means; ./c-64 names it
    here = tmp_path / "here"
    here.mkdir()
    (here / "c-64").write_bytes(b"not the shipped model")
    monkeypatch.chdir(here)
    with caplog.at_level(logging.WARNING):
        assert resolve_checkpoint("c-64", root) == root / "c-64.pt"
    assert "name the file ./c-64" in caplog.text
    assert resolve_checkpoint("./c-64", root).resolve() == here / "c-64"


def test_a_named_model_never_changes_size(root, monkeypatch):
    in_root(monkeypatch, root)
    for shape in ([256, 256], [64, 64], None):
        args = Namespace(checkpoint="c-64", image_shape=shape, images=["a.png", "b.png"])
        assert job_arguments.fit_checkpoint(args) == "c-64"


def test_commands_choose_the_default_for_the_request_and_say_so(root, monkeypatch, caplog):
    in_root(monkeypatch, root)
    caplog.set_level(logging.INFO, logger="usplat_dr.jobs.arguments")
    args = Namespace(checkpoint=None, image_shape=[128, 128], images=None)
    assert job_arguments.fit_checkpoint(args) == "c-128" and args.checkpoint == "c-128"
    assert "no --checkpoint: using c-128" in caplog.text
    # your own images without --image-shape: the largest
    args = Namespace(checkpoint=None, image_shape=None, images=["a.png", "b.png"])
    assert job_arguments.fit_checkpoint(args) == "c-256"


def test_usplat_models_lists_the_user_models_and_all_with_all(root, monkeypatch, capsys):
    monkeypatch.setattr(registry, "CHECKPOINTS", root)
    assert main(["models"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in out[:-1]] == ["c-64", "c-128", "c-256", "a-64"]
    assert out[0].startswith("c-64  (c)  64x64  p") and out[0].endswith("sha256 abababab")
    assert out[-1] == "(1 study models: usplat models --all)"
    assert main(["models", "--all"]) == 0
    assert capsys.readouterr().out.splitlines()[-1].split()[0] == "study/s"


def synth_root(path, shape, record=True):
    """A test stage of one scene whose images are stored at ``shape`` (H, W), with or without
    the ``synth.json`` that ``usplat synth`` writes."""
    from usplat_dr.data.chunks import encode_image, write_chunk, write_index
    test = path / "test"
    test.mkdir(parents=True)
    image = encode_image(np.zeros((*shape, 3), np.uint8))
    scene = {"key": "s", "url": "", "timestamps": torch.arange(2),
             "cameras": torch.zeros(2, 18), "images": [image, image]}
    write_chunk(test / "000000.torch", [scene])
    write_index(test, {"s": "000000.torch"})
    if record:
        (path / "synth.json").write_text(json.dumps({"resolution": list(shape)}))
    return path


def in_root(monkeypatch, root):
    """The render job's view of the shipped checkpoints: those of ``root``."""
    monkeypatch.setattr(job_arguments, "default_checkpoint",
                        lambda s: default_checkpoint(s, root=root))


@pytest.mark.parametrize("shape, record, expected", [
    ((128, 128), True, "c-128"), ((64, 64), True, "c-64"),
    ((128, 192), False, "c-128"),  # no synth.json: the first image's own size
    ((360, 640), False, "c-256")])  # RealEstate10K's frames: the largest that fits
def test_without_a_checkpoint_data_gets_the_c_of_its_stored_size(
        root, tmp_path, monkeypatch, shape, record, expected):
    in_root(monkeypatch, root)
    data = synth_root(tmp_path / "data", shape, record)
    assert stored_image_shape(data) == shape
    args = Namespace(checkpoint=None, image_shape=None, images=None, data=str(data))
    assert job_arguments.fit_checkpoint(args) == expected
    # --image-shape wins over the stored size
    args = Namespace(checkpoint=None, image_shape=[64, 64], images=None, data=str(data))
    assert job_arguments.fit_checkpoint(args) == "c-64"


def test_synth_json_is_read_before_the_images(tmp_path):
    # a set whose synth.json says 128x128 over images stored at 64x64: the record is what
    # usplat synth rendered at, read without loading a chunk
    data = synth_root(tmp_path / "data", (64, 64), record=False)
    (data / "synth.json").write_text(json.dumps({"resolution": [128, 128]}))
    assert stored_image_shape(data) == (128, 128)


def test_the_data_is_not_read_for_a_named_model(root, monkeypatch):
    in_root(monkeypatch, root)
    monkeypatch.setattr(job_arguments, "stored_image_shape",
                        lambda d: pytest.fail("read the data for a named model"))
    for name in ("c-64", str(root / "c-64.pt")):  # a name; a file
        args = Namespace(checkpoint=name, image_shape=None, images=None, data="d")
        assert job_arguments.fit_checkpoint(args) == name


def test_a_dataset_of_unreadable_size_gets_the_64x64_default(root, tmp_path, monkeypatch):
    in_root(monkeypatch, root)
    assert stored_image_shape(tmp_path / "missing") is None
    (tmp_path / "bad" / "test").mkdir(parents=True)
    (tmp_path / "bad" / "synth.json").write_text('{"resolution": "large"}')
    assert stored_image_shape(tmp_path / "bad") is None  # no chunk to read either
    args = Namespace(checkpoint=None, image_shape=None, images=None, data=str(tmp_path / "bad"))
    assert job_arguments.fit_checkpoint(args) == "c-64"


# ---- The shipped manifest -----------------------------------------------------------------

def test_the_shipped_manifest_has_at_most_one_a_and_one_c_per_size_for_users():
    models = shipped_models()
    users = [m for m in models.values() if m.kind == "user"]
    assert 1 <= len(users) <= 4
    pairs = [(m.variant, m.size) for m in users]
    assert len(set(pairs)) == len(pairs) and {v for v, _ in pairs} <= {"baseline", "full"}
    for m in models.values():
        # names say variant and size (users) or study/ (everything else)
        assert (re.fullmatch(r"(baseline|full)-[0-9]+", m.name) is not None) == (m.kind == "user")
        assert m.kind == "user" or m.name.startswith("study/")
        if m.kind == "user":
            assert m.name == f"{m.variant}-{m.size}"
        assert m.recipe and m.purpose and len(m.sha256) == 64
        assert m.old_names, m.name  # every shipped file had an earlier name
        if m.base is not None:
            assert m.base in models, (m.name, m.base)


def test_the_manifest_training_shapes_are_the_files_own():
    for name, m in shipped_models().items():
        assert min(training_image_shape(m.file)) == m.size, name


def test_the_commands_default_is_a_c_whose_branch_reads_live():
    entries = {e["name"]: e for e in json.loads((registry.CHECKPOINTS / "manifest.json")
                                                 .read_text())}
    for shape in ((64, 64), (128, 128), None):
        name = default_checkpoint(shape)[0]
        meter = entries[name]["view_specificity"]["splits"]
        assert shipped_models()[name].variant == "full"
        assert any(s["live"] and s["meter_low_db"] > 0 for s in meter.values()), name
