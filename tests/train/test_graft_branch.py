"""train/studies/graft_branch.py: the paper's start of a (c) from an (a), with the view-specific
branch's weights taken from another (c); the file starts a training run (model.init_from) as
it is, and the same command writes the same bytes."""

import importlib.util
from pathlib import Path

import pytest
import torch

from usplat_dr.training.checkpoints import (
    read_usplat_checkpoint,
    resolve_checkpoint,
    training_depth_range,
)
from usplat_dr.training.config import model_from_config

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "graft_branch.py"
spec = importlib.util.spec_from_file_location("graft_branch", SCRIPT)
graft_branch = importlib.util.module_from_spec(spec)
spec.loader.exec_module(graft_branch)

BRANCH = ("view_embedding.", "specific.")
#: H_a's embedding and hidden layers: random at the paper's start (one draw in the file, the
#: run's own draw in a (c) started from the (a) itself); the rest of the start is determined.
RANDOM_AT_START = ("agnostic.embedding", "agnostic.hyper.net.0.", "agnostic.hyper.net.2.")


@pytest.fixture(scope="module")
def grafted(tmp_path_factory):
    out = tmp_path_factory.mktemp("graft") / "graft.pt"
    donor = resolve_checkpoint("tiny_full")
    info = graft_branch.graft("tiny_baseline", str(donor), out)
    return out, donor, info


def test_the_branch_is_the_donors_and_the_rest_the_papers_start(grafted):
    out, donor, info = grafted
    state = torch.load(out, map_location="cpu", weights_only=True)  # plain data only
    g, d = state["model"], read_usplat_checkpoint(donor)["model"]
    start = model_from_config({"preset": "tiny", "variant": "full",
                               "init_from": "tiny_baseline"}).state_dict()
    branch = [k for k in g if k.startswith(BRANCH)]
    assert branch and info["branch_weights"] == len(branch)
    for k in branch:  # exactly the donor's (stored float16 there, float32 here)
        assert torch.equal(g[k], d[k].float()), k
    for k in g:
        if not k.startswith(BRANCH + RANDOM_AT_START):
            assert torch.equal(g[k], start[k]), k
    # the gate: the rows of H_s's last layer that make U and the bias deltas are zero at the
    # paper's start (those making V are random), and the donor's trained ones in the file
    last = max(k for k in branch if k.startswith("specific.") and k.endswith("weight"))
    gate = (start[last] == 0).all(dim=1)
    assert 0 < gate.sum() < len(gate), last
    assert g[last][gate].abs().max() > 0, last
    assert state["step"] == 0 and info["base"] == "tiny_baseline.pt"
    # the range the base trained on (tiny_baseline's is in its manifest entry)
    assert state["depth_range"] == list(training_depth_range("tiny_baseline"))


def test_a_run_started_from_it_has_its_weights_and_the_command_repeats(grafted, tmp_path):
    out, donor, _ = grafted
    model = model_from_config({"preset": "tiny", "variant": "full", "init_from": str(out)})
    g = torch.load(out, map_location="cpu", weights_only=True)["model"]
    for k, v in model.state_dict().items():
        assert torch.equal(v, g[k]), k
    again = tmp_path / "again.pt"
    graft_branch.graft("tiny_baseline", str(donor), again)
    assert again.read_bytes() == out.read_bytes()


def test_a_branch_that_is_not_a_c_is_named(tmp_path):
    with pytest.raises(SystemExit, match="--branch: .* is not a \\(c\\) checkpoint"):
        graft_branch.graft("tiny_baseline", str(resolve_checkpoint("tiny_baseline")),
                           tmp_path / "x.pt")
    with pytest.raises(SystemExit, match="--branch: nothing.pt does not exist"):
        graft_branch.graft("tiny_baseline", "nothing.pt", tmp_path / "x.pt")
    assert not (tmp_path / "x.pt").exists()
