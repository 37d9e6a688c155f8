"""Image metrics with the field's protocol (docs/field_protocol.md,
"Evaluation").

PSNR on images clipped to [0, 1]; SSIM through ``skimage.metrics.structural_similarity`` with
the field's arguments (Gaussian window sigma 1.5, 11 taps, data range 1, per channel on CHW
arrays, not clipped). ``ssim_torch`` is a differentiable twin for training losses.
"""

import numpy as np
import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor


def psnr(pred: Float[Tensor, "*batch 3 h w"], gt: Float[Tensor, "*batch 3 h w"]
         ) -> Float[Tensor, "*batch"]:
    """-10 log10(MSE) per image, both clipped to [0, 1] (the field's ``compute_psnr``).

    Examples:
        >>> round(psnr(torch.full((3, 4, 4), 0.1), torch.zeros(3, 4, 4)).item(), 4)
        20.0
    """
    mse = ((pred.clamp(0, 1) - gt.clamp(0, 1)) ** 2).mean(dim=(-3, -2, -1))
    return -10 * torch.log10(mse)


def ssim(pred: Float[Tensor, "*batch 3 h w"], gt: Float[Tensor, "*batch 3 h w"]
         ) -> Float[Tensor, "*batch"]:
    """SSIM per image exactly as the field computes it (scikit-image, float64)."""
    from skimage.metrics import structural_similarity  # on first use (start-up time)

    p = pred.detach().cpu().double().numpy().reshape(-1, *pred.shape[-3:])
    g = gt.detach().cpu().double().numpy().reshape(-1, *gt.shape[-3:])
    out = [structural_similarity(gi, pi, win_size=11, gaussian_weights=True, channel_axis=0,
                                 data_range=1.0) for pi, gi in zip(p, g)]
    return torch.tensor(np.array(out), dtype=torch.float32).reshape(pred.shape[:-3])


def _gaussian_window(size: int = 11, sigma: float = 1.5) -> Tensor:
    x = torch.arange(size, dtype=torch.float32) - size // 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return g / g.sum()


def ssim_torch(pred: Float[Tensor, "batch 3 h w"], gt: Float[Tensor, "batch 3 h w"]
               ) -> Float[Tensor, " batch"]:
    """Differentiable SSIM (Wang et al. 2004) with the same window and constants, averaged over
    the valid region (no padding) like scikit-image; it uses the population covariance, so it
    differs from ``ssim`` by the 121/120 sample factor only."""
    g = _gaussian_window().to(pred)
    c = pred.shape[1]
    wx = g.view(1, 1, 1, -1).expand(c, 1, 1, -1)
    wy = g.view(1, 1, -1, 1).expand(c, 1, -1, 1)

    def blur(x: Tensor) -> Tensor:
        return F.conv2d(F.conv2d(x, wx, groups=c), wy, groups=c)

    mu_p, mu_g = blur(pred), blur(gt)
    var_p = blur(pred * pred) - mu_p**2
    var_g = blur(gt * gt) - mu_g**2
    cov = blur(pred * gt) - mu_p * mu_g
    c1, c2 = 0.01**2, 0.03**2
    num = (2 * mu_p * mu_g + c1) * (2 * cov + c2)
    s = num / ((mu_p**2 + mu_g**2 + c1) * (var_p + var_g + c2))
    return s.mean(dim=(1, 2, 3))
