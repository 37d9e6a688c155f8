"""train/studies/auto_budget_proxy.py: the proxy and real losses are the PSNR differences the
study defines, context views against their own images, targets against theirs."""

import importlib.util
import math
from pathlib import Path
from types import SimpleNamespace

import torch

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "auto_budget_proxy.py"
spec = importlib.util.spec_from_file_location("auto_budget_proxy", SCRIPT)
study = importlib.util.module_from_spec(spec)
spec.loader.exec_module(study)


class Stub:
    """Renders a camera set as its reference image off by a known constant: 0.01 with every
    Gaussian; with a budget keeping f, 0.01 + (1 - f) / 10 on context views and 0.01 + (1 - f)
    / 20 on targets."""

    def __init__(self, context_image, target_image):
        self.context_image, self.target_image = context_image, target_image

    def encode(self, *args):
        return None

    def __call__(self, images, context, cameras, hooks=None, budget=None):
        is_context = cameras is context
        reference = self.context_image if is_context else self.target_image
        error = 0.01 + (0.0 if budget is None else (1 - budget.keep) / (10 if is_context else 20))
        return SimpleNamespace(color=reference + error)


def test_the_losses_are_the_psnr_differences():
    images = torch.full((1, 2, 3, 4, 4), 0.5)
    target = torch.full((1, 1, 3, 4, 4), 0.5)
    cams = SimpleNamespace(extrinsics=None, intrinsics=None, near=None, far=None)
    x = SimpleNamespace(images=images, context=cams, targets=SimpleNamespace())
    found = study.losses(Stub(images, target), x, target, (0.5,), "dither")
    # a constant error e gives PSNR -20 log10(e); float32 images: 1e-4 dB is ~10 ulp of 40 dB
    proxy, real = found[0.5]
    assert math.isclose(proxy, 20 * math.log10(0.06 / 0.01), abs_tol=1e-4)
    assert math.isclose(real, 20 * math.log10(0.035 / 0.01), abs_tol=1e-4)
    assert found[1.0] == (0.0, 0.0)
