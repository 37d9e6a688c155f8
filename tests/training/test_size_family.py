"""A shipped model's siblings trained at other sizes: the one that fits a render is chosen
(``fitting_checkpoint``) and said; files, and names without siblings, stay as named."""

import json
import logging
from argparse import Namespace

import numpy as np
import pytest
import torch

from usplat_dr.data.chunks import stored_image_shape
from usplat_dr.jobs import render as render_job
from usplat_dr.training import checkpoints
from usplat_dr.training.checkpoints import fitting_checkpoint, size_family


@pytest.fixture
def root(tmp_path):
    """A manifest of a family trained at 64, 128 and 256 (``m``, ``m_128``, ``m_256``), a
    ``m_stage1`` (not a size), and ``solo``."""
    entries = []
    for name, size in (("m", 64), ("m_128", 128), ("m_256", 256), ("m_stage1", 64),
                       ("solo", 64)):
        torch.save({"config": {"dataset": {"image_shape": [size, size]}}},
                   tmp_path / f"{name}.pt")
        entries.append({"name": name, "file": f"{name}.pt"})
    (tmp_path / "manifest.json").write_text(json.dumps(entries))
    return tmp_path


def test_the_family_is_the_name_and_its_sized_siblings(root):
    assert size_family("m", root) == {64: "m", 128: "m_128", 256: "m_256"}
    assert size_family("m_128", root) == size_family("m", root)
    assert size_family("m_stage1", root) == {64: "m_stage1"}  # "stage1" is no size
    assert size_family("nope", root) == {}


@pytest.mark.parametrize("shape, expected", [
    ((64, 64), "m"), ((128, 128), "m_128"), ((100, 200), "m_128"),  # the shorter side: 100
    ((90, 90), "m"),  # 90: 0.49 octaves above 64, 0.51 below 128
    ((512, 512), "m_256"), ((16, 16), "m"), (None, "m_256")])  # own photographs: the largest
def test_the_fitting_size_is_chosen_and_said(root, shape, expected):
    chosen, note = fitting_checkpoint("m", shape, root)
    assert chosen == expected
    assert (note is None) == (expected == "m")
    if note is not None:
        assert note.startswith(f"using {expected} (trained at ") and "for m:" in note


def test_files_lone_names_and_sized_names_stay(root):
    path = str(root / "m.pt")
    assert fitting_checkpoint(path, (256, 256), root) == (path, None)
    assert fitting_checkpoint("solo", (256, 256), root) == ("solo", None)
    # a name that gives a size is what the user asked for
    assert fitting_checkpoint("m_128", (64, 64), root) == ("m_128", None)
    assert fitting_checkpoint("m_256", None, root) == ("m_256", None)


def test_an_unreadable_sibling_is_left_out_and_said(root, caplog):
    (root / "m_256.pt").write_text("a Git LFS pointer, not a checkpoint")
    assert size_family("m", root) == {64: "m", 128: "m_128"}
    assert "leaving m_256 out of m's sizes" in caplog.text
    assert fitting_checkpoint("m", None, root)[0] == "m_128"


def test_commands_use_the_fitting_model_and_say_so(root, monkeypatch, caplog):
    monkeypatch.setattr(checkpoints, "CHECKPOINTS", root)
    monkeypatch.setattr(render_job, "fitting_checkpoint",
                        lambda c, s, **kw: fitting_checkpoint(c, s, root, **kw))
    caplog.set_level(logging.INFO, logger="usplat_dr.jobs.render")
    args = Namespace(checkpoint="m", image_shape=[128, 128], images=None)
    assert render_job.fit_checkpoint(args) == "m_128" and args.checkpoint == "m_128"
    assert "using m_128" in caplog.text
    # no --image-shape and no data: the named model at its own size
    args = Namespace(checkpoint="m", image_shape=None, images=None)
    assert render_job.fit_checkpoint(args) == "m" and args.checkpoint == "m"
    # your own images without --image-shape: the largest
    args = Namespace(checkpoint="m", image_shape=None, images=["a.png", "b.png"])
    assert render_job.fit_checkpoint(args) == "m_256"
    # a second model (the viewer's comparison) fitted the same way, --checkpoint left alone
    args = Namespace(checkpoint="solo", image_shape=[128, 128], images=None)
    assert render_job.fit_checkpoint(args, "m") == "m_128" and args.checkpoint == "solo"


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
    monkeypatch.setattr(render_job, "fitting_checkpoint",
                        lambda c, s, **kw: fitting_checkpoint(c, s, root, **kw))
    monkeypatch.setattr(render_job, "size_family", lambda n: size_family(n, root))


@pytest.mark.parametrize("shape, record, expected", [
    ((128, 128), True, "m_128"), ((64, 64), True, "m"),
    ((128, 192), False, "m_128"),  # no synth.json: the first image's own size
    ((360, 640), False, "m_256")])  # RealEstate10K's frames: the largest that fits
def test_data_without_a_shape_fits_the_size_its_images_are_stored_at(
        root, tmp_path, monkeypatch, shape, record, expected):
    in_root(monkeypatch, root)
    data = synth_root(tmp_path / "data", shape, record)
    assert stored_image_shape(data) == shape
    args = Namespace(checkpoint="m", image_shape=None, images=None, data=str(data))
    assert render_job.fit_checkpoint(args) == expected
    # --image-shape wins over the stored size
    args = Namespace(checkpoint="m", image_shape=[64, 64], images=None, data=str(data))
    assert render_job.fit_checkpoint(args) == "m"


def test_synth_json_is_read_before_the_images(tmp_path):
    # a set whose synth.json says 128x128 over images stored at 64x64: the record is what
    # usplat synth rendered at, read without loading a chunk
    data = synth_root(tmp_path / "data", (64, 64), record=False)
    (data / "synth.json").write_text(json.dumps({"resolution": [128, 128]}))
    assert stored_image_shape(data) == (128, 128)


def test_the_data_is_not_read_where_it_cannot_choose(root, tmp_path, monkeypatch):
    in_root(monkeypatch, root)
    monkeypatch.setattr(render_job, "stored_image_shape",
                        lambda d: pytest.fail("read the data for a name without siblings"))
    for name in ("solo", str(root / "m.pt")):  # no siblings; a file
        args = Namespace(checkpoint=name, image_shape=None, images=None, data="d")
        assert render_job.fit_checkpoint(args) == name


def test_a_dataset_of_unreadable_size_keeps_the_named_model(root, tmp_path, monkeypatch):
    in_root(monkeypatch, root)
    assert stored_image_shape(tmp_path / "missing") is None
    (tmp_path / "bad" / "test").mkdir(parents=True)
    (tmp_path / "bad" / "synth.json").write_text('{"resolution": "large"}')
    assert stored_image_shape(tmp_path / "bad") is None  # no chunk to read either
    args = Namespace(checkpoint="m", image_shape=None, images=None, data=str(tmp_path / "bad"))
    assert render_job.fit_checkpoint(args) == "m"


def test_the_shipped_families_have_their_128x128_members():
    # read from the shipped files' own configs (not the manifest's names): the (a), its budget
    # add-on and the (c) each have a member trained at 128x128, which own photographs get
    for name in ("tiny_baseline", "tiny_baseline_budget", "tiny_full"):
        assert size_family(name) == {64: name, 128: f"{name}_128"}, name
        assert fitting_checkpoint(name, None)[0] == f"{name}_128"
        assert fitting_checkpoint(name, (64, 64)) == (name, None)
    assert size_family("tiny_agnostic") == {64: "tiny_agnostic"}  # no sibling: as named
