"""The torch entry point of the rasteriser: the one module that imports both torch and drjit.

CPU tensors run on ``drjit.llvm.ad`` and CUDA tensors on ``drjit.cuda.ad``: ``drjit.wrap`` hands
the tensors over zero-copy (DLPack) on the same device, so there is no host round trip.
"""

import functools
import logging
from dataclasses import dataclass, field

import drjit as dr
import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from usplat_dr import _threads
from usplat_dr.backend import require_cuda, require_llvm
from usplat_dr.render.frozen import FrozenForward
from usplat_dr.render.pipeline import check_shapes, rasterize_drjit
from usplat_dr.render.settings import RasterSettings

log = logging.getLogger(__name__)


@dataclass
class RenderOutput:
    """``color`` [B, 3, H, W]; ``alpha`` [B, H, W] = 1 - final transmittance; ``depth`` [B, H, W]
    = sum of compositing weight x camera-space z of each Gaussian's centre (not divided by alpha,
    0 on background). ``aux``: debug values (``num_pairs``, ``tile_size``, ``radii`` [B, G])."""

    color: Float[Tensor, "batch 3 height width"]
    alpha: Float[Tensor, "batch height width"]
    depth: Float[Tensor, "batch height width"]
    aux: dict = field(default_factory=dict)


def check_inputs(extrinsics, intrinsics, near, far, image_shape, background_color, means,
                 covariances, sh_coefficients, opacities) -> None:
    """Raise ``ValueError`` naming the argument, what was expected and what came.

    Shapes follow the same rules as the Dr.Jit entry (``check_shapes``); here also the tensor
    type, dtype and device, and values (finite, near > 0, far > near) in one host read.
    """
    named = {"extrinsics": extrinsics, "intrinsics": intrinsics, "near": near, "far": far,
             "background_color": background_color, "means": means,
             "covariances": covariances, "sh_coefficients": sh_coefficients,
             "opacities": opacities}
    device = extrinsics.device if isinstance(extrinsics, torch.Tensor) else None
    for name, t in named.items():
        if not isinstance(t, torch.Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
        if t.dtype != torch.float32:
            raise ValueError(f"{name} must have dtype torch.float32, got {t.dtype} "
                             f"(convert with .float())")
        if t.device != device:
            raise ValueError(f"{name} must be on {device} like extrinsics, got {t.device}")
    check_shapes(image_shape, {name: t.shape for name, t in named.items()})
    flags = value_flags(list(named.values()), near, far)
    for ok, name in zip(flags, named):
        if not ok:
            raise ValueError(f"{name} must be finite, got NaN or Inf values")
    if not flags[-2]:
        raise ValueError(f"near must be > 0, got {near.detach().cpu().tolist()}")
    if not flags[-1]:
        raise ValueError(f"far must be > near, got near={near.detach().cpu().tolist()} "
                         f"far={far.detach().cpu().tolist()}")


def value_flags(tensors: list[Tensor], near: Tensor, far: Tensor) -> list[bool]:
    """Finite per tensor, then near > 0 and far > near, as Python booleans: the value checks
    of ``check_inputs`` (which names what failed), on their own (train/bench/rasterizer.py
    times them).

    On the CPU the checks run in NumPy on the tensors' own memory: a torch reduction over a
    few hundred thousand values is split across torch's OpenMP threads, and on a loaded
    2-core machine waiting for the second core cost about 21 ms per call; NumPy takes
    0.1-0.4 ms (train/bench/README.md, "The torch bridge"). On a GPU the checks stay on the
    device with one host read for all of them.

    Examples:
        >>> near, far = torch.ones(1), torch.full((1,), 2.0)
        >>> value_flags([torch.zeros(2), torch.tensor([float("nan")])], near, far)
        [True, False, True, True]
    """
    if near.device.type == "cpu":
        arrays = [t.detach().numpy() for t in tensors]
        n, f = near.detach().numpy(), far.detach().numpy()
        return ([bool(np.isfinite(a).all()) for a in arrays]
                + [bool((n > 0).all()), bool((f > n).all())])
    flags = torch.stack([torch.isfinite(t.detach()).all() for t in tensors]
                        + [(near.detach() > 0).all(), (far.detach() > near.detach()).all()])
    return flags.cpu().tolist()


@functools.lru_cache(maxsize=64)
def _wrapped(image_shape: tuple[int, int], settings: RasterSettings):
    """The torch <-> Dr.Jit boundary for one image shape and settings.

    Non-tensor arguments are closed over rather than passed: ``drjit.wrap`` traverses its
    arguments as PyTrees (a dataclass would be rebuilt with gradient values).
    """

    frozen = FrozenForward(image_shape, settings) if settings.freeze_forward else None

    @dr.wrap(source="torch", target="drjit")
    def render(extrinsics, intrinsics, near, far, background_color, means, covariances,
               sh_coefficients, opacities):
        args = (extrinsics, intrinsics, near, far, background_color, means, covariances,
                sh_coefficients, opacities)
        if frozen is not None and not any(dr.grad_enabled(t) for t in args[5:]):
            return frozen(*args)
        out = rasterize_drjit(extrinsics, intrinsics, near, far, image_shape, background_color,
                              means, covariances, sh_coefficients, opacities, settings,
                              check=False)
        return out.color, out.alpha, out.depth, out.aux["radii"], out.aux["num_pairs"]

    return render


@functools.cache
def _warn_spinning_openmp() -> None:
    """Once per process, where torch was imported before ``usplat_dr`` and runs more than one
    thread: its OpenMP workers then spin for milliseconds after each operation (libgomp's
    default) on the cores Dr.Jit's threads need (``usplat_dr._threads``)."""
    if torch.get_num_threads() > 1 and _threads.torch_came_first():
        log.warning("torch was imported before usplat_dr, so its OpenMP threads spin for "
                    "milliseconds after each operation on the cores the rasteriser needs "
                    "(up to 2x slower at 2 threads): import usplat_dr before torch, or set "
                    "GOMP_SPINCOUNT=30000 in the environment")


def rasterize(
    extrinsics: Float[Tensor, "batch 4 4"],
    intrinsics: Float[Tensor, "batch 3 3"],
    near: Float[Tensor, " batch"],
    far: Float[Tensor, " batch"],
    image_shape: tuple[int, int],
    background_color: Float[Tensor, "batch 3"],
    means: Float[Tensor, "batch gaussian 3"],
    covariances: Float[Tensor, "batch gaussian 3 3"],
    sh_coefficients: Float[Tensor, "batch gaussian 3 d_sh"],
    opacities: Float[Tensor, "batch gaussian"],
    settings: RasterSettings | None = None,
) -> RenderOutput:
    """Render 3D Gaussians as the 3DGS CUDA rasteriser does when pixelSplat/MVSplat call it.

    The argument conventions of the field's ``render_cuda``: ``extrinsics`` camera-to-world,
    OpenCV axes (x right, y down, z forward); ``intrinsics`` normalised by image width (row 0) and
    height (row 1); ``sh_coefficients`` with D = (degree + 1)^2 coefficients, degree 0..4 (degree
    4 accepted and ignored, as the reference does). Differentiable with respect to means,
    covariances (upper triangle), SH coefficients and opacities. CPU tensors render on Dr.Jit's
    LLVM backend, CUDA tensors on its CUDA backend. See ``RasterSettings`` for the options.

    Examples:
        >>> import torch
        >>> from usplat_dr.render import rasterize
        >>> eye = torch.eye(4)[None]
        >>> K = torch.tensor([[[1.0, 0, 0.5], [0, 1, 0.5], [0, 0, 1]]])
        >>> means = torch.tensor([[[0.0, 0, 2]]], requires_grad=True)
        >>> out = rasterize(eye, K, torch.tensor([0.1]), torch.tensor([10.0]), (8, 8),
        ...                 torch.zeros(1, 3), means, 0.01 * torch.eye(3)[None, None],
        ...                 torch.ones(1, 1, 3, 1), torch.tensor([[0.9]]))
        >>> out.color.shape, round(out.alpha[0, 3, 3].item(), 2)
        (torch.Size([1, 3, 8, 8]), 0.52)
        >>> out.depth.sum().backward()
        >>> means.grad.shape
        torch.Size([1, 1, 3])
    """
    check_inputs(extrinsics, intrinsics, near, far, image_shape, background_color, means,
                 covariances, sh_coefficients, opacities)
    settings = settings or RasterSettings()
    if extrinsics.device.type == "cuda":
        require_cuda()
    elif extrinsics.device.type == "cpu":
        require_llvm()
        _warn_spinning_openmp()
    else:
        raise ValueError(f"tensors must be on a CPU or CUDA device, got {extrinsics.device}")
    b, g = means.shape[:2]
    if g == 0:
        # Nothing to rasterise: the background, with the graph kept so .backward() still works.
        h, w = image_shape
        zero = means.sum() + covariances.sum() + sh_coefficients.sum() + opacities.sum()
        color = background_color[:, :, None, None].expand(b, 3, h, w) + 0 * zero
        blank = torch.zeros(b, h, w, device=means.device) + 0 * zero
        return RenderOutput(color=color, alpha=blank, depth=blank.clone(),
                            aux={"num_pairs": 0, "radii": torch.zeros(b, 0)})
    tensors = [t.contiguous() for t in (extrinsics, intrinsics, near, far, background_color,
                                        means, covariances, sh_coefficients, opacities)]
    color, alpha, depth, radii, num_pairs = _wrapped(tuple(image_shape), settings)(*tensors)
    return RenderOutput(color=color, alpha=alpha, depth=depth,
                        aux={"num_pairs": num_pairs, "radii": radii.reshape(b, g)})
