"""LPIPS-VGG: torchvision/lpips weight layouts load strictly, a clear error names a missing
file, and the distance equals a float64 computation written from the paper's equations."""

import pytest
import torch
import torch.nn.functional as F

from usplat_dr.evaluation.lpips import LPIPS, TAP_CHANNELS, VGG16_LAYOUT, LPIPSWeightsMissing
from usplat_dr.model.checkpoint import CheckpointMismatchError


def weight_files(tmp_path, seed: int = 0):
    """A torchvision-layout VGG16 state dict (features + classifier, as the real file) and an
    lpips-layout linear state dict, with random values."""
    g = torch.Generator().manual_seed(seed)
    vgg, c, i = {}, 3, 0
    for item in VGG16_LAYOUT:
        if item == "M":
            i += 1
            continue
        vgg[f"features.{i}.weight"] = torch.randn(item, c, 3, 3, generator=g) / (3 * c**0.5)
        vgg[f"features.{i}.bias"] = 0.01 * torch.randn(item, generator=g)
        c, i = item, i + 2
    vgg["classifier.0.weight"] = torch.zeros(4, 4)  # ignored: only features are used
    lin = {f"lin{k}.model.1.weight": torch.rand(1, ch, 1, 1, generator=g)
           for k, ch in enumerate(TAP_CHANNELS)}
    torch.save(vgg, tmp_path / "vgg16.pth")
    torch.save(lin, tmp_path / "vgg.pth")
    return tmp_path / "vgg16.pth", tmp_path / "vgg.pth", vgg, lin


def reference(vgg: dict, lin: dict, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """LPIPS from its definition, float64: scale to [-1, 1], shift/scale per channel, VGG16
    conv3x3+ReLU stack with 2x2 max pools, at relu1_2..relu5_3 unit-normalise over channels,
    squared difference, weighted sum over channels (w_l), spatial mean, sum over layers."""
    shift = torch.tensor([-0.030, -0.088, -0.188], dtype=torch.float64).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450], dtype=torch.float64).view(1, 3, 1, 1)

    def feats(img):
        h = ((2 * img.double() - 1) - shift) / scale
        out, idx = [], 0
        blocks = [2, 2, 3, 3, 3]  # convs per VGG16 block
        for nconv in blocks:
            for _ in range(nconv):
                h = F.relu(F.conv2d(h, vgg[f"features.{idx}.weight"].double(),
                                    vgg[f"features.{idx}.bias"].double(), padding=1))
                idx += 2
            out.append(h)
            h = F.max_pool2d(h, 2)
            idx += 1
        return out

    total = 0
    for k, (a, b) in enumerate(zip(feats(x), feats(y))):
        a = a / (a.norm(dim=1, keepdim=True) + 1e-10)
        b = b / (b.norm(dim=1, keepdim=True) + 1e-10)
        w = lin[f"lin{k}.model.1.weight"].double().view(1, -1, 1, 1)
        total = total + ((a - b) ** 2 * w).sum(1).mean((-2, -1))
    return total


def test_lpips_matches_the_definition(tmp_path):
    vgg_path, lin_path, vgg, lin = weight_files(tmp_path)
    model = LPIPS.from_files(vgg_path, lin_path)
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2, 3, 48, 48, generator=g)
    y = (x + 0.1 * torch.randn(2, 3, 48, 48, generator=g)).clamp(0, 1)
    with torch.no_grad():
        d = model(x, y)
    ref = reference(vgg, lin, x, y)
    # float32 VGG against float64: ~1e-6 relative; 1e-4 is loose enough for any BLAS and
    # far below the distance itself (~1e-1 here).
    assert torch.allclose(d.double(), ref, rtol=1e-4), (d, ref)
    assert d.min() > 1e-3
    assert torch.allclose(model(x, x), torch.zeros(2), atol=1e-7)  # identical images
    assert torch.allclose(model(y, x), d, rtol=1e-5)  # symmetric
    model.train()
    assert not model.training  # dropout never switches on


def test_lpips_weight_files_are_checked(tmp_path):
    vgg_path, lin_path, _vgg, lin = weight_files(tmp_path)
    with pytest.raises(LPIPSWeightsMissing, match="vgg16-397923af.pth"):
        LPIPS.from_files(tmp_path / "nope.pth", lin_path)
    with pytest.raises(LPIPSWeightsMissing, match="lpips/weights/v0.1/vgg.pth"):
        LPIPS.from_files(vgg_path, None)
    del lin["lin3.model.1.weight"]
    torch.save(lin, tmp_path / "bad.pth")
    with pytest.raises(CheckpointMismatchError, match="lin3.model.1.weight"):
        LPIPS.from_files(vgg_path, tmp_path / "bad.pth")
