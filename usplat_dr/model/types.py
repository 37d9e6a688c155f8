"""The one crossing between encoder and renderer (pixelSplat's ``Gaussians``)."""

from dataclasses import dataclass

from jaxtyping import Float
from torch import Tensor


@dataclass
class Gaussians:
    """World-space 3D Gaussians of a batch of scenes.

    ``means`` [B, G, 3]; ``covariances`` [B, G, 3, 3]; ``harmonics`` [B, G, 3, d_sh] (colour,
    coefficient; e3nn order as MVSplat); ``opacities`` [B, G] in [0, 1]; ``scales`` [B, G, 3] and
    ``rotations`` [B, G, 4] (unit quaternions, xyzw) in the camera frame of the view that
    predicted each Gaussian (MVSplat's ``visualization_dump``). G is ordered view-major, then
    pixel in raster order, then Gaussian-per-pixel.
    """

    means: Float[Tensor, "batch gaussian 3"]
    covariances: Float[Tensor, "batch gaussian 3 3"]
    harmonics: Float[Tensor, "batch gaussian 3 d_sh"]
    opacities: Float[Tensor, "batch gaussian"]
    scales: Float[Tensor, "batch gaussian 3"]
    rotations: Float[Tensor, "batch gaussian 4"]

    def __len__(self) -> int:
        return self.means.shape[1]

    def scaled(self, factor: Float[Tensor, " batch"]) -> "Gaussians":
        """The same Gaussians in a world scaled by ``factor`` (one per batch entry) about its
        origin: means and scales times ``factor``, covariances times its square."""
        f = factor.to(self.means.dtype)
        return Gaussians(means=self.means * f[:, None, None],
                         covariances=self.covariances * (f * f)[:, None, None, None].to(
                             self.covariances.dtype),
                         harmonics=self.harmonics, opacities=self.opacities,
                         scales=self.scales * f[:, None, None].to(self.scales.dtype),
                         rotations=self.rotations)
