"""LPIPS-VGG (Zhang et al. 2018, ``lpips`` v0.1), as the field evaluates and trains with it.

Our own network definition; weights come from two files the user provides (nothing is
downloaded): torchvision's VGG16 ImageNet weights (``vgg16-397923af.pth``, keys
``features.N.weight``) and the LPIPS linear layers (``vgg.pth`` shipped in the ``lpips`` pip
package under ``lpips/weights/v0.1/``, keys ``linK.model.1.weight``).

    d = LPIPS.from_files(vgg_path, lin_path)(pred, gt)  # images in [0, 1], [B, 3, H, W]
"""

import os
from pathlib import Path

import torch
from jaxtyping import Float
from torch import Tensor, nn

from usplat_dr.io.checkpoint_files import load_torch_file
from usplat_dr.model.checkpoint import check_state_dict

# torchvision's vgg16 ``features``: channel counts, "M" = max pool.
VGG16_LAYOUT = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M",
                512, 512, 512, "M")
# LPIPS taps relu1_2, relu2_2, relu3_3, relu4_3, relu5_3: ``features`` indices of those ReLUs.
TAPS = (3, 8, 15, 22, 29)
TAP_CHANNELS = (64, 128, 256, 512, 512)
# lpips' ScalingLayer (inputs in [-1, 1]).
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)

VGG_HINT = ("torchvision's VGG16 ImageNet weights (vgg16-397923af.pth, from "
            "https://download.pytorch.org/models/)")
LIN_HINT = "the LPIPS linear weights (lpips/weights/v0.1/vgg.pth in the lpips pip package)"


class LPIPSWeightsMissing(FileNotFoundError):
    """An LPIPS weight file is not there; the message says which file to provide."""


class VGG16Features(nn.Module):
    """torchvision's ``vgg16().features`` (same module indices, so its weights load)."""

    def __init__(self):
        super().__init__()
        layers, c = [], 3
        for item in VGG16_LAYOUT:
            if item == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers += [nn.Conv2d(c, item, 3, padding=1), nn.ReLU(inplace=False)]
                c = item
        self.features = nn.Sequential(*layers)

    def taps(self, x: Tensor) -> list[Tensor]:
        """The activations after the ReLUs that LPIPS compares (``TAPS``), shallow to deep."""
        out = []
        for i, layer in enumerate(self.features[:TAPS[-1] + 1]):
            x = layer(x)
            if i in TAPS:
                out.append(x)
        return out


class _Linear(nn.Module):
    """lpips' ``NetLinLayer``: dropout (inactive at evaluation) and a 1x1 conv to 1 channel."""

    def __init__(self, channels: int):
        super().__init__()
        self.model = nn.Sequential(nn.Dropout(), nn.Conv2d(channels, 1, 1, bias=False))


class LPIPS(nn.Module):
    """LPIPS distance per image pair: ``forward(pred, gt)`` with images in [0, 1]."""

    def __init__(self):
        super().__init__()
        self.net = VGG16Features()
        for i, c in enumerate(TAP_CHANNELS):
            self.add_module(f"lin{i}", _Linear(c))
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    @classmethod
    def from_files(cls, vgg_path: str | os.PathLike | None, lin_path: str | os.PathLike | None
                   ) -> "LPIPS":
        """The network with both weight files loaded strictly; ``LPIPSWeightsMissing`` names
        the file that is missing."""
        for path, hint, name in ((vgg_path, VGG_HINT, "vgg"), (lin_path, LIN_HINT, "lin")):
            if path is None or not Path(path).is_file():
                raise LPIPSWeightsMissing(
                    f"LPIPS needs {hint}; {str(path)!r} is not a file. Provide it "
                    f"(training: loss.lpips_{name}=FILE; usplat eval: --lpips-{name} FILE) or "
                    f"turn LPIPS off (loss.lpips=0)")
        model = cls()
        vgg = _state_dict(vgg_path, "VGG16 weights")
        vgg = {k: v for k, v in vgg.items() if k.startswith("features.")}
        check_state_dict(model.net, vgg, what=f"VGG16 weights {vgg_path}")
        model.net.load_state_dict(vgg, strict=True)
        lin = _state_dict(lin_path, "LPIPS linear weights")
        lin_modules = nn.ModuleDict({f"lin{i}": getattr(model, f"lin{i}") for i in range(5)})
        check_state_dict(lin_modules, lin, what=f"LPIPS linear weights {lin_path}")
        lin_modules.load_state_dict(lin, strict=True)
        return model

    def train(self, mode: bool = True) -> "LPIPS":
        """Always in evaluation mode (its dropout is part of the published training only)."""
        return super().train(False)

    def forward(self, pred: Float[Tensor, "batch 3 h w"], gt: Float[Tensor, "batch 3 h w"]
                ) -> Float[Tensor, " batch"]:
        """The LPIPS distance of each image pair (inputs in [0, 1]; lower is closer)."""
        x = ((2 * pred - 1) - self.shift) / self.scale
        y = ((2 * gt - 1) - self.shift) / self.scale
        total = 0
        for i, (fx, fy) in enumerate(zip(self.net.taps(x), self.net.taps(y))):
            fx = fx / (fx.square().sum(1, keepdim=True).sqrt() + 1e-10)
            fy = fy / (fy.square().sum(1, keepdim=True).sqrt() + 1e-10)
            d = getattr(self, f"lin{i}").model((fx - fy).square())
            total = total + d.mean((-2, -1))
        return total[:, 0]


def _state_dict(path: str | os.PathLike, what: str) -> dict:
    """A weight file as a dict of tensors, read safely (``load_torch_file``: a file that is
    not a torch file, or holds code, is an error naming it)."""
    state = load_torch_file(path, what)
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor)
                                              for v in state.values()):
        raise ValueError(f"{what} {str(path)!r} is not a state dict (names -> tensors)")
    return state
