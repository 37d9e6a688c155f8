"""UniqueSplat's hypernetwork branches: ``resnet.ResNet18`` (E_H), ``epipolar`` (Proj),
``view_branch`` (E_H + Proj + phi -> e_s), ``hypernetwork`` (H_a, H_s and the layouts of the
weights they generate) and ``injection`` (target layers run with W + Delta W per target)."""
