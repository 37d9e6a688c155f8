"""A (c) whose view-specific branch starts open: the paper's start from a trained (a) with the
branch's weights taken from another, trained (c).

The paper's protocol starts (c) from (a): the primary network from (a), H_a's bias W from (a)'s
head weights and the hypernetworks' outputs at zero, so the model starts exactly as (a) and
its view-specific branch starts closed (no gradient reaches E_H, Proj or phi until H_s's
last layer has grown). This writes that start with the branch, ``view_embedding.*`` (E_H, Proj,
phi) and ``specific.*`` (H_s), replaced by the branch of ``--branch``, a (c) whose branch is
live; H_a stays the paper's start (its bias W the (a)'s head weights; its embedding and
hidden layers one random draw, torch seed 0). Every weight of the branch is free of the image
size (convolutions, MLPs), so a branch trained at 64x64 loads into a start for 128x128 as it
is. The file is in
the shipped weights' format (float32, loadable with ``torch.load(weights_only=True)``), its
training config and depth range the base's, so ``model.init_from=OUT`` starts a (c) from it
(``usplat_dr.training.checkpoints.init_from_checkpoint``: the same variant and config, every
weight matched).

    git show 301d7e8:train/studies/beyond/full_seed_3_step300.pt > DONOR.pt  # the 64x64 (c)
    python train/studies/graft_branch.py --base tiny_baseline_128 --branch DONOR.pt \\
        --out outputs/beyond128_graft/graft.pt

(train/studies/LOG.md, "(c) at 128x128 with its branch started open").
"""

import argparse
import sys
from pathlib import Path

import torch

import usplat_dr  # noqa: F401  (libLLVM first)
from usplat_dr.io.atomic import torch_save
from usplat_dr.io.user_files import sha256
from usplat_dr.model.uniquesplat import UniqueSplat, UniqueSplatCfg
from usplat_dr.training.checkpoints import (
    MAX_CHECKPOINT_BYTES,
    init_from_checkpoint,
    read_usplat_checkpoint,
    resolve_checkpoint,
    training_depth_range,
)

#: The view-specific branch's weights: E_H, Proj and phi (``view_embedding``) and H_s.
BRANCH = ("view_embedding.", "specific.")


def graft(base: str, branch: str, out: str | Path) -> dict:
    """Write the start described above to ``out``; returns its ``metadata["graft"]``."""
    base_path = resolve_checkpoint(base) if not Path(base).is_file() else Path(base)
    branch_path = Path(branch)
    if not branch_path.is_file():
        raise SystemExit(f"--branch: {branch} does not exist (give a (c) checkpoint file whose "
                         f"view-specific branch is live, e.g. a verdict run's step-300 export)")
    donor = read_usplat_checkpoint(branch_path)
    cfg_dict = donor.get("model_config")
    if not isinstance(cfg_dict, dict) or cfg_dict.get("variant") != "full":
        raise SystemExit(f"--branch: {branch} is not a (c) checkpoint (its model_config's "
                         f"variant is {cfg_dict and cfg_dict.get('variant')!r}, not 'full')")
    cfg = UniqueSplatCfg.from_dict({**cfg_dict, "resnet_weights": None})
    # H_a's embedding and hidden layers are random at the paper's start (its last layer zero,
    # its bias W): one fixed draw, so the same command writes the same file (the caller's
    # random state left as it was)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = UniqueSplat(cfg)
    init_from_checkpoint(model, base_path)  # the paper's start: the branch closed
    own = model.state_dict()
    taken = {k: v.float() for k, v in donor["model"].items() if k.startswith(BRANCH)}
    mine = sorted(k for k in own if k.startswith(BRANCH))
    if sorted(taken) != mine or any(own[k].shape != v.shape for k, v in taken.items()):
        raise SystemExit(f"--branch: {branch}'s view-specific branch does not fit the model "
                         f"its own config describes")
    model.load_state_dict(taken, strict=False)
    base_state = read_usplat_checkpoint(base_path)
    limit = MAX_CHECKPOINT_BYTES
    info = {"base": base_path.name, "base_sha256": sha256(base_path, "--base", limit),
            "branch": branch_path.name, "branch_sha256": sha256(branch_path, "--branch", limit),
            "branch_step": donor.get("step", 0), "branch_weights": len(taken)}
    state = {"format": "usplat-weights/1",
             "model": {k: v.contiguous() for k, v in model.state_dict().items()},
             "model_config": cfg.to_dict(), "config": base_state.get("config", {}), "step": 0,
             "provenance": base_state.get("provenance", {}), "metadata": {"graft": info}}
    depth_range = training_depth_range(base_path)  # its own, else its manifest entry's
    if depth_range is not None:
        state["depth_range"] = list(depth_range)
    torch_save(state, out)
    return info


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--base", required=True,
                   help="the (a) to start from: a shipped name or a usplat checkpoint file")
    p.add_argument("--branch", required=True,
                   help="a (c) checkpoint file whose view-specific branch to take")
    p.add_argument("--out", required=True, help="the start to write (.pt)")
    args = p.parse_args(argv)
    info = graft(args.base, args.branch, args.out)
    print(f"wrote {args.out}: {info['base']} with the view-specific branch of {info['branch']} "
          f"(step {info['branch_step']}, {info['branch_weights']} tensors)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
