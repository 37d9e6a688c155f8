"""The shipped checkpoints: every manifest entry's file exists, matches its sha256, stays
within the size budget, loads with weights_only (plain data, nothing executed) and renders;
(b) and (c) name the (a) they were fine-tuned from; the registry
(``usplat_dr.training.checkpoints``) reads them."""

import hashlib
import json
import logging
import math
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import torch

from usplat_dr.data.synth.scenes import KINDS, make_spec
from usplat_dr.geometry.cameras import Cameras
from usplat_dr.model import UniqueSplat
from usplat_dr.training.checkpoints import (
    BASE,
    BUDGETED,
    SHIPPED,
    depth_range_warning,
    load_model,
    registered_verdict,
    shipped_checkpoints,
    training_depth_range,
)

ROOT = Path(__file__).parents[2] / "checkpoints"
MANIFEST = json.loads((ROOT / "manifest.json").read_text())
KEYS = {"name", "preset", "variant", "file", "sha256", "train_command", "data", "steps",
        "metrics"}
#: The budget for shipped weights (they live in the repository and the wheel; docs/model.md):
#: 25 MB until the 128x128 models, 40 MB since (the tiny (a) is 3.5 MB at any size, the (c)
#: 7.3 MB, in float16). The GPU path's carry (64 MiB with the repository, its data and the
#: drjit wheel) holds a 128x128 (a) beside what ships; a 128x128 (c) needs less data carried.
MAX_BYTES = 40 * 10**6


@pytest.fixture(autouse=True)
def _quiet_resnet(caplog):
    caplog.set_level(logging.ERROR, logger="usplat_dr.model.hypernet.resnet")


def test_manifest_lists_the_required_models_within_budget():
    names = {e["name"] for e in MANIFEST}
    assert {"baseline-64", "full-64"} <= names
    assert all(KEYS <= set(e) for e in MANIFEST), [KEYS - set(e) for e in MANIFEST]
    assert sum((ROOT / e["file"]).stat().st_size for e in MANIFEST) <= MAX_BYTES
    by = {e["name"]: e for e in MANIFEST}
    files = {e["file"] for e in MANIFEST}
    for e in MANIFEST:
        if e.get("base"):
            # an add-on (the budget stage): fine-tuned from the shipped file it is stored on
            assert Path(e["init_from"]).name == by[e["base"]]["file"], e["name"]
        elif e["variant"] != "baseline" or e["name"].endswith("_continued"):
            # (b), (c) and the control: fine-tuned by the paper's protocol from the shipped (a)
            # of their size (study/tiny_full_128 from study/tiny_baseline_128)
            size = min(e["training_shape"])
            a_file = "tiny_baseline.pt" if size == 64 else f"tiny_baseline_{size}.pt"
            assert a_file in files and Path(e["init_from"]).name == a_file, e["name"]
        elif e.get("init_from_commit"):
            # a staged (a) started from an earlier version of a file: named by commit and hash
            assert re.fullmatch(r"[0-9a-f]{7,40}", e["init_from_commit"]), e["name"]
            assert re.fullmatch(r"[0-9a-f]{64}", e["init_from_sha256"]), e["name"]
        elif e.get("init_from"):
            # a staged (a): its ancestry starts at a shipped checkpoint
            assert Path(e["init_from"]).name in files, e["name"]


def test_the_shipped_depth_range_is_that_of_the_scene_kinds_they_trained_on():
    # every shipped model trained on `usplat synth` sets of the three kinds; the generator's
    # own near_far records (independent of the manifest) give the range
    ranges = [make_spec(kind, seed, 24)["near_far"] for kind in KINDS for seed in (0, 1)]
    expected = [min(r[0] for r in ranges), max(r[0] for r in ranges),
                min(r[1] for r in ranges), max(r[1] for r in ranges)]
    for name in shipped_checkpoints():
        assert training_depth_range(name) == expected, name
    # what render and view read: the loaded model carries it (one read of the file)
    assert load_model(shipped_checkpoints()["baseline-64"])[0].trained_depth_range == expected
    # a room in the synthetic kinds' units passes; the same room in millimetres does not
    assert depth_range_warning(0.2, 20.0, expected) is None
    assert "far outside" in depth_range_warning(200.0, 20000.0, expected)
    assert depth_range_warning(1e-3, 1e9, None) is None  # nothing recorded: nothing to say


def test_the_registry_names_shipped_files(tmp_path):
    """``shipped_checkpoints`` and ``registered_verdict`` read this folder (the default root in a
    source checkout); the names the demo starts from are in the manifest."""
    shipped = shipped_checkpoints(ROOT)
    assert {BASE, *SHIPPED.values(), *BUDGETED.values()} <= set(shipped)
    assert shipped == {e["name"]: ROOT / e["file"] for e in MANIFEST}
    assert set(shipped_checkpoints()) == set(shipped)
    assert registered_verdict(ROOT) == json.loads((ROOT / "verdict.json").read_text())
    assert registered_verdict(tmp_path) is None
    with pytest.raises(FileNotFoundError, match="manifest.json"):
        shipped_checkpoints(tmp_path)


def in_history(commit: str) -> bool:
    """Whether this checkout's git history holds ``commit`` (not in a wheel install or a
    shallow clone)."""
    if shutil.which("git") is None or not (ROOT.parent / ".git").exists():
        return False
    command = ["git", "-C", str(ROOT.parent), "cat-file", "-e", f"{commit}^{{commit}}"]
    return subprocess.run(command, capture_output=True, check=False).returncode == 0


@pytest.mark.parametrize("entry", [e for e in MANIFEST if e.get("init_from_commit")],
                         ids=lambda e: e["name"])
def test_an_init_from_git_history_matches_its_sha256(entry):
    # the earlier file a stage started from is still in the history, byte for byte
    if not in_history(entry["init_from_commit"]):
        pytest.skip(f"commit {entry['init_from_commit']} is not in this checkout's history "
                    f"(a wheel install or a shallow clone)")
    data = subprocess.run(["git", "-C", str(ROOT.parent), "show",
                           f"{entry['init_from_commit']}:{entry['init_from']}"],
                          capture_output=True, check=True).stdout
    assert hashlib.sha256(data).hexdigest() == entry["init_from_sha256"]


@pytest.mark.parametrize("entry", MANIFEST, ids=[e["name"] for e in MANIFEST])
def test_entry_matches_its_sha256_and_loads(entry):
    path = ROOT / entry["file"]
    assert hashlib.sha256(path.read_bytes()).hexdigest() == entry["sha256"]
    state = torch.load(path, map_location="cpu", weights_only=True)  # plain data only
    assert "optimizer" not in state and state["format"] == "usplat-weights/1"
    model, step = load_model(path)
    assert model.cfg.variant == entry["variant"] and step >= 1
    # an add-on (its base's model with the budget stage's importance head, or with another
    # view-specific branch) says so in the manifest and in the file; an importance head ships
    # only as an add-on
    assert bool(entry.get("base")) == ("base" in state)
    assert not model.cfg.importance or "base" in state
    reference = UniqueSplat.from_preset(entry["preset"], variant=entry["variant"],
                                        importance=model.cfg.importance,
                                        importance_hidden=model.cfg.importance_hidden,
                                        view_features=model.cfg.view_features)
    assert sum(p.numel() for p in model.parameters()) == sum(
        p.numel() for p in reference.parameters())
    # a render on two cameras a short baseline apart: finite, in range
    g = torch.Generator().manual_seed(0)
    k = torch.tensor([[0.9, 0, 0.5], [0, 0.9, 0.5], [0, 0, 1.0]])
    e = torch.eye(4).repeat(1, 3, 1, 1)
    e[0, 1, 0, 3], e[0, 2, 0, 3] = 0.2, 0.1
    images = torch.rand(1, 2, 3, 32, 32, generator=g)
    with torch.no_grad():
        out = model(images, Cameras(e[:, :2], k.expand(1, 2, 3, 3), torch.full((1, 2), 0.5),
                                    torch.full((1, 2), 20.0)),
                    Cameras(e[:, 2:], k.expand(1, 1, 3, 3), torch.full((1, 1), 0.5),
                            torch.full((1, 1), 20.0)))
    assert torch.isfinite(out.color).all() and out.color.shape == (1, 1, 3, 32, 32)
    assert math.isfinite(entry["metrics"]["splits"]["standard"]["psnr"])
