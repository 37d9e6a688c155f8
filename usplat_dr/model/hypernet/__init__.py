"""UniqueSplat's hypernetwork branches (issue 5, in progress): ``resnet.ResNet18`` (E_H) and
``epipolar.EpipolarProjection`` (Proj). The hypernetworks and the injection come next."""
