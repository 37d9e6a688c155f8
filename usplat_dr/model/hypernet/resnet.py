"""ResNet18 (He et al. 2016) with torchvision's module names, so torchvision-format ImageNet
weight files (``resnet18-f37072fd.pth``) load strictly; torchvision itself is not needed.

UniqueSplat's view-specific branch uses it as the feature extractor E_H (paper: a pretrained
ResNet18); ``features`` returns the stride-4 ``layer1`` to stride-32 ``layer4`` maps.
"""

import logging
import os
from pathlib import Path

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from usplat_dr.io.checkpoint_files import load_torch_file
from usplat_dr.model.checkpoint import check_state_dict

log = logging.getLogger(__name__)


class BasicBlock(nn.Module):
    def __init__(self, in_planes: int, planes: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(in_planes, planes, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample = None
        if stride != 1 or in_planes != planes:
            self.downsample = nn.Sequential(nn.Conv2d(in_planes, planes, 1, stride, bias=False),
                                            nn.BatchNorm2d(planes))

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return F.relu(y + (x if self.downsample is None else self.downsample(x)))


class ResNet18(nn.Module):
    """torchvision's ``resnet18`` layout (11,689,512 parameters with the 1000-class ``fc``).

    Examples:
        >>> net = ResNet18()
        >>> sum(p.numel() for p in net.parameters())
        11689512
        >>> [f.shape[1] for f in net.features(torch.rand(1, 3, 64, 64))]
        [64, 128, 256, 512]
    """

    IMAGENET_MEAN = (0.485, 0.456, 0.406)
    IMAGENET_STD = (0.229, 0.224, 0.225)

    def __init__(self, num_classes: int | None = 1000, stages: int = 4):
        super().__init__()
        if not 1 <= stages <= 4:
            raise ValueError(f"stages must be in 1..4, got {stages}")
        if num_classes is not None and stages != 4:
            raise ValueError("the classifier (num_classes) needs all 4 stages; pass "
                             "num_classes=None for a truncated feature extractor")
        self.stages = stages
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        planes = [64, 128, 256, 512]
        self.channels = planes[:stages]
        for i in range(stages):
            stride, inp = (1, 64) if i == 0 else (2, planes[i - 1])
            self.add_module(f"layer{i + 1}", nn.Sequential(BasicBlock(inp, planes[i], stride),
                                                           BasicBlock(planes[i], planes[i])))
        self.fc = nn.Linear(planes[-1], num_classes) if num_classes is not None else None
        for m in self.modules():  # torchvision's initialisation
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
        self.register_buffer("mean", torch.tensor(self.IMAGENET_MEAN).view(3, 1, 1),
                             persistent=False)
        self.register_buffer("std", torch.tensor(self.IMAGENET_STD).view(3, 1, 1),
                             persistent=False)

    def features(self, images: Float[Tensor, "n 3 h w"]) -> list[Tensor]:
        """``layer1``..``layer<stages>`` outputs (strides 4, 8, 16, 32) of images in [0, 1]."""
        x = (images - self.mean) / self.std
        x = self.maxpool(F.relu(self.bn1(self.conv1(x))))
        out = []
        for i in range(self.stages):
            x = getattr(self, f"layer{i + 1}")(x)
            out.append(x)
        return out

    def forward(self, images: Float[Tensor, "n 3 h w"]) -> Float[Tensor, "n classes"]:
        if self.fc is None:
            raise RuntimeError("this ResNet18 has no classifier (num_classes=None); use "
                               "features()")
        x = self.features(images)[-1]
        return self.fc(torch.flatten(F.adaptive_avg_pool2d(x, 1), 1))

    def load_torchvision(self, path: str | os.PathLike | None) -> bool:
        """Load a torchvision-format ResNet18 weight file (``resnet18-f37072fd.pth``): every
        weight this network has must be in the file with its shape; the file's weights of
        parts this network lacks (``fc`` without a classifier, stages beyond ``stages``) are
        ignored. ``None`` or a missing file: keep the random initialisation and log a warning
        (returns False); a file that does not fit raises with the mismatching keys."""
        if path is None or not Path(path).is_file():
            log.warning("ResNet18 weights %s not found: the view-specific branch starts from "
                        "random initialisation (pass a torchvision resnet18 .pth file, e.g. "
                        "resnet18-f37072fd.pth, for the paper's ImageNet-pretrained backbone)",
                        path)
            return False
        sd = load_torch_file(path, "ResNet18 weights")  # not a torch file: an error naming it
        if not isinstance(sd, dict):
            raise ValueError(f"ResNet18 weights {str(path)!r} are not a state dict (names -> "
                             f"tensors)")
        absent = {"fc"} if self.fc is None else set()
        absent |= {f"layer{i + 1}" for i in range(self.stages, 4)}
        sd = {k: v for k, v in sd.items() if k.split(".")[0] not in absent}
        check_state_dict(self, sd, what=f"ResNet18 weights {path}")
        self.load_state_dict(sd, strict=True)
        return True
