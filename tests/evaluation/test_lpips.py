"""LPIPS-VGG: torchvision/lpips weight layouts load strictly, a clear error names a missing
file, and the distance equals a float64 computation written from the paper's equations and the
``lpips`` package (v0.1.4) itself on the same weights."""

import importlib.util
import sys
import types
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from torch import nn

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


def vgg16_standin(pretrained: bool = False, weights=None, **_kwargs) -> nn.Module:
    """torchvision's ``models.vgg16`` as far as lpips uses it (``.features``), written from the
    published architecture (Simonyan & Zisserman 2015, Table 1, configuration D): 13 3x3 convs
    (padding 1), each followed by a ReLU, in blocks of 2, 2, 3, 3, 3 convs, each block closed by
    a 2x2 max pool of stride 2; module order as torchvision's, so ``features.N`` indices match."""
    if pretrained or weights is not None:
        raise AssertionError("the stand-in has no ImageNet weights (lpips would download them)")
    layers, c_in = [], 3
    for c_out, convs in ((64, 2), (128, 2), (256, 3), (512, 3), (512, 3)):
        for _ in range(convs):
            layers += [nn.Conv2d(c_in, c_out, kernel_size=3, padding=1), nn.ReLU(inplace=True)]
            c_in = c_out
        layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
    net = nn.Module()
    net.features = nn.Sequential(*layers)
    return net


@pytest.fixture
def lpips_package(monkeypatch):
    """The real ``lpips`` package (its own code: scaling layer, trunk slices, normalisation,
    linear layers, spatial mean), imported against a stand-in ``torchvision``.

    lpips imports ``torchvision.models`` for its trunk, and the only torchvision wheels the
    package index offers for our torch are CUDA builds that do not load with the CPU torch, so
    ``torchvision`` here is a module with one function, ``vgg16_standin`` above, put into
    ``sys.modules`` for this test only (lpips is imported afresh, and removed afterwards)."""
    if importlib.util.find_spec("lpips") is None:
        pytest.skip("the lpips package is not installed (bash scripts/run.sh setup installs it; "
                    "by hand: pip install --no-deps -c constraints.txt lpips)")
    for name in list(sys.modules):
        if name.split(".")[0] in ("lpips", "torchvision"):
            monkeypatch.delitem(sys.modules, name)
    models = types.ModuleType("torchvision.models")
    models.vgg16 = vgg16_standin
    torchvision = types.ModuleType("torchvision")
    torchvision.models = models
    monkeypatch.setitem(sys.modules, "torchvision", torchvision)
    monkeypatch.setitem(sys.modules, "torchvision.models", models)
    import lpips

    yield lpips
    for name in list(sys.modules):
        if name.split(".")[0] == "lpips":
            del sys.modules[name]


@pytest.mark.parametrize("lin_weights", ["random", "lpips v0.1 file"])
def test_lpips_equals_the_lpips_package(tmp_path, lpips_package, lin_weights):
    """Random VGG16 weights (no weight file is given) copied into both networks; the linear
    layers random too, or each network loads the lpips package's own ``weights/v0.1/vgg.pth``."""
    vgg_path, lin_path, _vgg, _lin = weight_files(tmp_path, seed=2)
    if lin_weights != "random":
        lin_path = Path(lpips_package.__file__).parent / "weights" / "v0.1" / "vgg.pth"
    ours = LPIPS.from_files(vgg_path, lin_path)
    theirs = lpips_package.LPIPS(net="vgg", version="0.1", pretrained=lin_weights != "random",
                                 pnet_rand=True, verbose=False)
    mine = ours.state_dict()
    state = {}
    for key, value in theirs.state_dict().items():
        if key.startswith("net.slice"):  # net.slice2.5.weight: torchvision's features.5.weight
            _net, _slice, index, param = key.split(".")
            state[key] = mine[f"net.features.{index}.{param}"]
        elif key.startswith("lins."):  # lins.k aliases link (the same module)
            _lins, k, rest = key.split(".", 2)
            state[key] = value if lin_weights != "random" else mine[f"lin{k}.{rest}"]
        elif key.startswith("lin"):
            state[key] = value if lin_weights != "random" else mine[key]
        else:  # scaling_layer.shift / .scale: lpips's own constants, compared with ours
            state[key] = value
    theirs.load_state_dict(state, strict=True)
    for k in range(5):  # with the package's file, each network loaded it on its own
        assert torch.equal(getattr(theirs, f"lin{k}").model[1].weight,
                           getattr(ours, f"lin{k}").model[1].weight)
    g = torch.Generator().manual_seed(3)
    x = torch.rand(3, 3, 64, 64, generator=g)
    y = torch.cat([torch.rand(1, 3, 64, 64, generator=g),  # unrelated, noisy, identical
                   (x[1:2] + 0.05 * torch.randn(1, 3, 64, 64, generator=g)).clamp(0, 1), x[2:]])
    with torch.no_grad():
        d = ours(x, y)
        ref = theirs(x, y, normalize=True)  # normalize: inputs in [0, 1], as ours
    assert ref.shape == (3, 1, 1, 1)
    # The same float32 operations in the same order on the same weights (the stand-in only
    # lays the layers out); 1e-6 relative allows for a different summation order in a kernel.
    assert torch.allclose(d, ref.flatten(), rtol=1e-6, atol=1e-9), (d, ref.flatten())
    assert d[0] > d[1] > 0 and d[2] == 0
