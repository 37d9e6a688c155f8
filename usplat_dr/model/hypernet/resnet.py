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

    def __init__(self, num_classes: int = 1000):
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        planes = [64, 128, 256, 512]
        self.layer1 = nn.Sequential(BasicBlock(64, 64), BasicBlock(64, 64))
        self.layer2 = nn.Sequential(BasicBlock(64, 128, 2), BasicBlock(128, 128))
        self.layer3 = nn.Sequential(BasicBlock(128, 256, 2), BasicBlock(256, 256))
        self.layer4 = nn.Sequential(BasicBlock(256, 512, 2), BasicBlock(512, 512))
        self.fc = nn.Linear(planes[-1], num_classes)
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
        """``layer1``..``layer4`` outputs (strides 4, 8, 16, 32) of images in [0, 1]."""
        x = (images - self.mean) / self.std
        x = self.maxpool(F.relu(self.bn1(self.conv1(x))))
        out = []
        for layer in (self.layer1, self.layer2, self.layer3, self.layer4):
            x = layer(x)
            out.append(x)
        return out

    def forward(self, images: Float[Tensor, "n 3 h w"]) -> Float[Tensor, "n classes"]:
        x = self.features(images)[-1]
        return self.fc(torch.flatten(F.adaptive_avg_pool2d(x, 1), 1))

    def load_torchvision(self, path: str | os.PathLike | None, strict_fc: bool = True
                         ) -> bool:
        """Load a torchvision-format ResNet18 weight file. ``None`` or a missing file: keep the
        random initialisation and log a warning (returns False); a file that does not fit
        raises with the mismatching keys."""
        if path is None or not Path(path).is_file():
            log.warning("ResNet18 weights %s not found: the view-specific branch starts from "
                        "random initialisation (pass a torchvision resnet18 .pth file, e.g. "
                        "resnet18-f37072fd.pth, for the paper's ImageNet-pretrained backbone)",
                        path)
            return False
        from usplat_dr.model.checkpoint import check_state_dict

        sd = torch.load(path, map_location="cpu", weights_only=True)
        if not strict_fc:
            sd = {**sd, **{k: v for k, v in self.state_dict().items() if k.startswith("fc.")}}
        check_state_dict(self, sd, what=f"ResNet18 weights {path}")
        self.load_state_dict(sd, strict=True)
        return True
