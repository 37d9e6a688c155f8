"""``usplat synth`` keeps a root's train and test stages apart: per-stage default seeds,
per-stage metadata files, and a refusal to write scenes the other stage already holds."""

import hashlib
import json

import pytest

from usplat_dr.cli import main
from usplat_dr.data.synth import DEFAULT_SEEDS, default_seed, metadata_folder, synthesize

TINY = ["--scenes", "2", "--frames", "4", "--image-shape", "8", "8", "--spp", "1",
        "--kind", "object", "--previews", "1"]


def _synth(root, *args) -> int:
    return main(["-q", "synth", "--out", str(root), *TINY, *args])


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.parametrize(("stage", "seed", "chunk", "index"), [
    # sha256 of the chunk and index.json before per-stage seeds and metadata existed: the
    # published sets and checkpoints were made with explicit seeds (100 train, 2000 test),
    # which must keep their bytes (the diffuse direct integrator is exact, so bit for bit).
    ("train", 100, "b02f67ac6a3dcc6078f9635275dd99bd224558ed095d59981bffc0e9fc374492",
     "4c4e74216d106256da1ba8e6ccd445d1ff1868443c373fcb1f6577deb30d06fb"),
    ("test", 2000, "9dc561170cffb73290c97327dc21dd5a348da56f407cc3dff5872dca0a1ec080",
     "5852be633a4cec861a28435c1ecb8fbf829b0ee25685622a8761fd9d4db271be"),
])
def test_an_explicit_seed_keeps_its_bytes(tmp_path, stage, seed, chunk, index):
    synthesize(tmp_path, scenes=2, frames=4, resolution=(16, 16), seed=seed, spp=2,
               stage=stage, previews=0, progress=False)
    assert _sha(tmp_path / stage / "000000.torch") == chunk
    assert _sha(tmp_path / stage / "index.json") == index


def test_default_seeds_differ_and_stages_keep_their_own_files(tmp_path):
    assert default_seed("train") != default_seed("test") and DEFAULT_SEEDS["test"] == 0
    assert _synth(tmp_path, "--stage", "test") == 0
    before = {p.relative_to(tmp_path): _sha(p) for p in tmp_path.rglob("*") if p.is_file()}
    assert _synth(tmp_path, "--stage", "train") == 0
    after = {p.relative_to(tmp_path): _sha(p) for p in tmp_path.rglob("*") if p.is_file()}
    assert {k: after[k] for k in before} == before  # the train run changed no test file
    test_keys = json.loads((tmp_path / "test" / "index.json").read_text())
    train_keys = json.loads((tmp_path / "train" / "index.json").read_text())
    assert sorted(test_keys) == ["object_0_00000", "object_0_00001"]
    assert not set(test_keys) & set(train_keys)
    train_meta = metadata_folder(tmp_path, "train")
    assert train_meta == tmp_path / "train"
    assert json.loads((train_meta / "synth.json").read_text())["seed"] == DEFAULT_SEEDS["train"]
    assert json.loads((tmp_path / "synth.json").read_text())["stage"] == "test"
    std = json.loads((train_meta / "evaluation_index_standard.json").read_text())
    assert sorted(std) == sorted(train_keys)
    assert (train_meta / "splits.json").is_file()
    assert (train_meta / "previews" / "object_1_00000.png").is_file()


@pytest.mark.parametrize("first", ["test", "train"])
def test_a_stage_sharing_the_other_stages_scenes_is_refused(tmp_path, capsys, first):
    other = {"test": "train", "train": "test"}[first]
    assert _synth(tmp_path, "--stage", first, "--seed", "0") == 0
    capsys.readouterr()
    files = sorted(p for p in tmp_path.rglob("*"))
    assert _synth(tmp_path, "--stage", other, "--seed", "0") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert str(tmp_path) in err and f"its {first} stage already holds 2 of these scenes" in err
    assert "--seed" in err and "object_0_00000" in err
    assert sorted(p for p in tmp_path.rglob("*")) == files  # nothing written
    # the view-dependent appearance of the same seed has the same geometry and cameras
    assert _synth(tmp_path, "--stage", other, "--seed", "0", "--appearance",
                  "view-dependent") == 2
    # another seed (or the other stage's default) is fine
    assert _synth(tmp_path, "--stage", other, "--seed", "5") == 0
