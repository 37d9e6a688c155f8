"""Strict loading of MVSplat checkpoints, the reverse export, and the GMDepth backbone."""

import pytest
import torch

from tests.model.conftest import MANIFEST, inputs
from usplat_dr.model import (
    CheckpointMismatchError,
    PrimaryNetwork,
    PrimaryNetworkCfg,
    export_mvsplat_checkpoint,
    load_gmdepth_backbone,
    load_mvsplat_state_dict,
)


def manifest() -> dict[str, tuple[int, ...]]:
    rows = MANIFEST.read_text().splitlines()[1:]
    return {k: tuple(int(s) for s in shape.split("x")) for k, shape, _ in
            (r.split("\t") for r in rows)}


def test_keys_and_shapes_equal_the_official_manifest():
    net = PrimaryNetwork()
    ours = {"encoder." + k: tuple(v.shape) for k, v in net.state_dict().items()}
    assert ours == manifest()
    assert len(ours) == 471
    assert sum(p.numel() for p in net.parameters()) == 11_955_734


def test_lightning_checkpoint_file_loads_strictly(tmp_path, weights):
    path = tmp_path / "re10k.ckpt"
    torch.save({"state_dict": {"encoder." + k: v for k, v in weights.items()},
                "global_step": 300_000, "epoch": 3}, path)
    net = PrimaryNetwork.from_mvsplat_checkpoint(path)
    for k, v in net.state_dict().items():
        assert torch.equal(v, weights[k]), k


def test_bare_state_dict_with_or_without_prefix(weights):
    net = PrimaryNetwork()
    load_mvsplat_state_dict(net, weights)
    assert torch.equal(net.state_dict()["depth_predictor.to_gaussians.2.bias"],
                       weights["depth_predictor.to_gaussians.2.bias"])
    load_mvsplat_state_dict(net, {"encoder." + k: v for k, v in weights.items()})


def test_mismatch_lists_missing_unexpected_and_shapes(weights):
    bad = dict(weights)
    del bad["backbone.backbone.conv1.weight"]
    bad["depth_predictor.extra.weight"] = torch.zeros(1)
    bad["depth_predictor.to_disparity.2.weight"] = torch.zeros(6, 64, 3, 3)
    with pytest.raises(CheckpointMismatchError) as err:
        load_mvsplat_state_dict(PrimaryNetwork(), bad)
    msg = str(err.value)
    assert "1 missing keys" in msg and "backbone.backbone.conv1.weight" in msg
    assert "1 unexpected keys" in msg and "depth_predictor.extra.weight" in msg
    assert "to_disparity.2.weight: checkpoint [6, 64, 3, 3] vs network [2, 64, 3, 3]" in msg


def test_missing_file_and_bad_types_are_clear(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.ckpt"):
        PrimaryNetwork.from_mvsplat_checkpoint(tmp_path / "nope.ckpt")
    with pytest.raises(ValueError, match="path or a dict"):
        PrimaryNetwork.from_mvsplat_checkpoint(3)
    with pytest.raises(ValueError, match="state dict"):
        load_mvsplat_state_dict(PrimaryNetwork(), {"state_dict": {"a": 1}})


def test_export_round_trip_gives_the_same_gaussians(tmp_path, net, fixture_dev):
    path = export_mvsplat_checkpoint(net, tmp_path / "ours.ckpt", global_step=7)
    ckpt = torch.load(path, weights_only=True)
    assert all(k.startswith("encoder.") for k in ckpt["state_dict"]) and ckpt["global_step"] == 7
    again = PrimaryNetwork.from_mvsplat_checkpoint(path).eval()
    with torch.no_grad():
        a, b = net(*inputs(fixture_dev)), again(*inputs(fixture_dev))
    assert torch.equal(a.means, b.means) and torch.equal(a.harmonics, b.harmonics)


def test_ablation_layout_refuses_the_full_checkpoint(weights):
    cfg = PrimaryNetworkCfg(use_depth_refine=False)
    with pytest.raises(CheckpointMismatchError, match="200 unexpected keys"):
        load_mvsplat_state_dict(PrimaryNetwork(cfg), weights)


def test_gmdepth_backbone(tmp_path):
    source = PrimaryNetwork()
    sd = {k: v.clone() for k, v in source.backbone.state_dict().items()}
    sd["upsampler.0.weight"] = torch.zeros(3)  # GMDepth keys we do not use are ignored
    path = tmp_path / "gmdepth.pth"
    torch.save({"model": sd}, path)
    net = load_gmdepth_backbone(PrimaryNetwork(), path)
    for k, v in source.backbone.state_dict().items():
        assert torch.equal(net.backbone.state_dict()[k], v), k
    del sd["transformer.layers.5.cross_attn_ffn.norm2.bias"]
    torch.save({"model": sd}, path)
    with pytest.raises(CheckpointMismatchError, match="norm2.bias"):
        load_gmdepth_backbone(PrimaryNetwork(), path)
