"""The primary network: an MVSplat-equivalent encoder (``EncoderCostVolume``) that loads the
official checkpoints strictly and computes the same Gaussians."""

import types
import typing
from dataclasses import dataclass, fields, replace
from math import lcm

import torch
from jaxtyping import Float
from torch import Tensor, nn

from usplat_dr.model.checkpoint import load_mvsplat_state_dict
from usplat_dr.model.encoder.backbone import BackboneMultiview
from usplat_dr.model.encoder.depth_predictor import DepthOutputs, DepthPredictorMultiView
from usplat_dr.model.gaussian_adapter import GaussianAdapter
from usplat_dr.model.types import Gaussians


def check_finite(**tensors) -> None:
    """ValueError naming the first argument holding NaN or Inf (one reduction per tensor)."""
    for name, t in tensors.items():
        if not bool(torch.isfinite(t).all()):
            bad = int((~torch.isfinite(t)).sum())
            raise ValueError(f"{name} holds {bad} NaN or Inf value(s); replace them (e.g. "
                             f"torch.nan_to_num for images) or drop the scene")


def config_from_dict(cls, d: dict):
    """A frozen config dataclass from plain values (YAML/JSON): unknown keys are an error
    naming the known ones; lists become tuples; missing keys keep their defaults."""
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ValueError(f"unknown {cls.__name__} keys {unknown}; known: {sorted(known)}")
    d = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
    hints = typing.get_type_hints(cls)
    for name, value in d.items():
        if not _fits(hints[name], value):
            raise ValueError(f"{cls.__name__}.{name} must be of type {_type_name(hints[name])}, "
                             f"got {value!r:.80}")
    return replace(cls(), **d)


def _fits(hint, value) -> bool:
    """Whether a plain value fits a config field's annotation (int, float, str, bool, a nested
    config, ``X | None``, ``tuple[X, ...]``, ``tuple[X, Y, Z]``)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_fits(a, value) for a in args)
    if origin is tuple:
        if not isinstance(value, tuple):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_fits(args[0], v) for v in value)
        return len(args) == len(value) and all(_fits(a, v) for a, v in zip(args, value))
    if hint is type(None):
        return value is None
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, hint)


def _type_name(hint) -> str:
    return getattr(hint, "__name__", None) or str(hint).replace("typing.", "")


#: Longest list a config's list fields may hold (U-Net levels, attention resolutions, the
#: hypernetwork's channels): the presets use <= 5.
MAX_LIST = 8


def check_bounds(cfg, bounds: dict[str, int]) -> None:
    """``ValueError`` unless every field named in ``bounds`` is an int (or a tuple of at most
    ``MAX_LIST`` ints) in 0..bound. The bounds are ~16x the paper's sizes: a config from a
    checkpoint or a YAML file is refused before a module is built, instead of building 10^6
    layers."""
    for name, hi in bounds.items():
        value = getattr(cfg, name)
        items = value if isinstance(value, tuple) else (value,)
        if isinstance(value, tuple) and len(value) > MAX_LIST:
            raise ValueError(f"{name} has {len(value)} entries, more than {MAX_LIST}")
        for v in items:
            if v is None and not isinstance(value, tuple):
                continue
            if isinstance(v, bool) or not isinstance(v, int):
                # a config error, like every other (the CLI reports ValueErrors in one line)
                raise ValueError(f"{name} must hold integers, got {value!r}")
            if not 0 <= v <= hi:
                raise ValueError(f"{name} must be in 0..{hi}, got {v}")


@dataclass(frozen=True)
class PrimaryNetworkCfg:
    """MVSplat's encoder settings; the defaults are its RealEstate10K configuration
    (``+experiment=re10k``; ACID and DTU use the same architecture)."""

    d_feature: int = 128
    downscale_factor: int = 4  # the CNN's 1/4 resolution; fixed by its layout
    num_transformer_layers: int = 6
    ffn_expansion: int = 4
    multiview_trans_attn_split: int = 2
    num_depth_candidates: int = 128
    costvolume_unet_feat_dim: int = 128
    costvolume_unet_channel_mult: tuple[int, ...] = (1, 1, 1)
    costvolume_unet_attn_res: tuple[int, ...] = (4,)
    depth_unet_feat_dim: int = 32
    depth_unet_channel_mult: tuple[int, ...] = (1, 1, 1, 1, 1)
    depth_unet_attn_res: tuple[int, ...] = (16,)
    gaussians_per_pixel: int = 1
    sh_degree: int = 4
    # The SH degree the colours use (None: sh_degree). Lower than sh_degree, the head keeps
    # its outputs (and a checkpoint's shapes) and the adapter zeroes the coefficients above
    # it: degree 0 is colour that cannot change with the viewpoint, the control that measures
    # how much view-dependent colour a split needs.
    colour_sh_degree: int | None = None
    gaussian_scale_min: float = 0.5
    gaussian_scale_max: float = 15.0
    # Opacity mapping 0.5 (1 - (1-p)^e + p^(1/e)), e = 2^x, x from initial to final over
    # warm_up steps; MVSplat ships 0/0, i.e. opacity = density.
    opacity_mapping: tuple[float, float, int] = (0.0, 0.0, 1)
    # Ablation switches (MVSplat sec. 4.3). Our layouts: a switched-off part has no keys and the
    # remaining shapes are unchanged; MVSplat's own ablation checkpoints are not supported.
    use_cross_view_attention: bool = True  # False: the transformer's cross layer sees its view
    use_cost_volume: bool = True  # False: zero correlation, features only
    use_cost_volume_refine: bool = True  # False: only the 1x1 skip refines the cost volume
    use_depth_refine: bool = True  # False: the heads take proj_feature instead of the U-Net
    # How the plane sweep is computed (same numbers to float32 rounding): "gram" from
    # pixel-pair dot products (fast), "warp" by warping features like the reference, in
    # chunks of cost_volume_chunk depth candidates (memory).
    cost_volume_method: str = "gram"
    cost_volume_chunk: int = 16

    def __post_init__(self):
        check_bounds(self, {"d_feature": 2048, "num_transformer_layers": 64, "ffn_expansion": 16,
                            "multiview_trans_attn_split": 64, "num_depth_candidates": 2048,
                            "costvolume_unet_feat_dim": 2048, "costvolume_unet_channel_mult": 16,
                            "costvolume_unet_attn_res": 4096, "depth_unet_feat_dim": 2048,
                            "depth_unet_channel_mult": 16, "depth_unet_attn_res": 4096,
                            "gaussians_per_pixel": 16, "cost_volume_chunk": 2048})
        for name in ("d_feature", "num_transformer_layers", "num_depth_candidates",
                     "costvolume_unet_feat_dim", "depth_unet_feat_dim", "gaussians_per_pixel",
                     "multiview_trans_attn_split", "cost_volume_chunk"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.downscale_factor != 4:
            raise ValueError(f"downscale_factor must be 4 (the CNN's layout), got "
                             f"{self.downscale_factor}")
        if self.cost_volume_method not in ("gram", "warp"):
            raise ValueError(f"cost_volume_method must be 'gram' or 'warp', got "
                             f"{self.cost_volume_method!r}")
        if not 0 <= self.sh_degree <= 4:
            raise ValueError(f"sh_degree must be in 0..4, got {self.sh_degree}")
        if self.colour_sh_degree is not None and not 0 <= self.colour_sh_degree <= self.sh_degree:
            raise ValueError(f"colour_sh_degree must be in 0..sh_degree={self.sh_degree} or "
                             f"None, got {self.colour_sh_degree}")
        if self.depth_unet_feat_dim % 4 or self.costvolume_unet_feat_dim % 8:
            raise ValueError("depth_unet_feat_dim must be a multiple of 4 and "
                             "costvolume_unet_feat_dim a multiple of 8 (GroupNorm groups)")

    @property
    def image_multiple(self) -> int:
        """Image height and width must be multiples of this (U-Net levels, attention windows)."""
        cv = 4 * 2 ** (len(self.costvolume_unet_channel_mult) - 1)
        refine = 2 ** (len(self.depth_unet_channel_mult) - 1) if self.use_depth_refine else 1
        return lcm(cv, refine, 8 * self.multiview_trans_attn_split)

    @classmethod
    def from_dict(cls, d: dict) -> "PrimaryNetworkCfg":
        return config_from_dict(cls, d)


class PrimaryNetwork(nn.Module):
    """MVSplat's encoder. ``forward(images, extrinsics, intrinsics, near, far) -> Gaussians``.

    State-dict keys are MVSplat's with the ``encoder.`` prefix stripped (471 keys for the
    default configuration). Build from a checkpoint with ``from_mvsplat_checkpoint``.

    Examples:
        >>> import torch
        >>> net = PrimaryNetwork().eval()
        >>> sum(p.numel() for p in net.parameters())
        11955734
        >>> e = torch.eye(4).repeat(1, 2, 1, 1); e[0, 1, 0, 3] = 0.1
        >>> k = torch.tensor([[0.9, 0, 0.5], [0, 0.9, 0.5], [0, 0, 1]]).repeat(1, 2, 1, 1)
        >>> with torch.no_grad():
        ...     g = net(torch.rand(1, 2, 3, 32, 32), e, k, torch.ones(1, 2), 100 * torch.ones(1, 2))
        >>> g.means.shape, g.harmonics.shape
        (torch.Size([1, 2048, 3]), torch.Size([1, 2048, 3, 25]))
    """

    def __init__(self, config: PrimaryNetworkCfg | None = None):
        super().__init__()
        cfg = config or PrimaryNetworkCfg()
        self.cfg = cfg
        self.backbone = BackboneMultiview(cfg.d_feature, cfg.num_transformer_layers,
                                          cfg.ffn_expansion, cfg.use_cross_view_attention)
        self.depth_predictor = DepthPredictorMultiView(cfg)
        self.gaussian_adapter = GaussianAdapter(cfg.sh_degree, cfg.gaussian_scale_min,
                                                cfg.gaussian_scale_max, cfg.colour_sh_degree)

    @classmethod
    def from_mvsplat_checkpoint(cls, checkpoint, config: PrimaryNetworkCfg | None = None,
                                map_location="cpu") -> "PrimaryNetwork":
        """Build the network and load an official MVSplat checkpoint (a path to a Lightning
        ``.ckpt``, such a dict, or a bare state dict, with or without ``encoder.``) strictly."""
        net = cls(config)
        load_mvsplat_state_dict(net, checkpoint, map_location=map_location)
        return net

    def opacity_exponent(self, global_step: int) -> float:
        x0, x1, warm_up = self.cfg.opacity_mapping
        x = x0 + min(global_step / warm_up, 1) * (x1 - x0)
        return 2.0**x

    def check_inputs(self, images, extrinsics, intrinsics, near, far) -> None:
        if images.ndim != 5 or images.shape[2] != 3:
            raise ValueError(f"images must have shape [B, V, 3, H, W], got {tuple(images.shape)}")
        b, v, _, h, w = images.shape
        if v < 2:
            raise ValueError(f"images must hold >= 2 context views, got {v}")
        m = self.cfg.image_multiple
        if h % m or w % m:
            raise ValueError(f"images height and width must be multiples of {m}, got {h}x{w}; "
                             f"centre-crop them (usplat_dr.data.shims.rescale_and_crop)")
        for name, t, shape in (("extrinsics", extrinsics, (b, v, 4, 4)),
                               ("intrinsics", intrinsics, (b, v, 3, 3)),
                               ("near", near, (b, v)), ("far", far, (b, v))):
            if tuple(t.shape) != shape:
                raise ValueError(f"{name} must have shape {list(shape)}, got {list(t.shape)}")
        check_finite(images=images, extrinsics=extrinsics, intrinsics=intrinsics, near=near,
                     far=far)
        if (near <= 0).any() or (far <= near).any():
            raise ValueError("near must be > 0 and far > near for every view")

    def encode(self, images: Float[Tensor, "b v 3 h w"], extrinsics: Float[Tensor, "b v 4 4"],
               intrinsics: Float[Tensor, "b v 3 3"], near: Float[Tensor, "b v"],
               far: Float[Tensor, "b v"], run_heads: bool = True
               ) -> tuple[Tensor, Tensor, DepthOutputs]:
        """Backbone and depth predictor: (transformer features, CNN features, depth outputs);
        ``run_heads=False`` stops before the depth and Gaussian heads."""
        self.check_inputs(images, extrinsics, intrinsics, near, far)
        trans, cnn = self.backbone(images, self.cfg.multiview_trans_attn_split)
        out = self.depth_predictor(trans, cnn, images, extrinsics, intrinsics, near, far,
                                   run_heads)
        return trans, cnn, out

    def gaussians_from(self, depth: DepthOutputs, extrinsics: Float[Tensor, "b v 4 4"],
                       intrinsics: Float[Tensor, "b v 3 3"],
                       image_shape: tuple[int, int], global_step: int = 0) -> Gaussians:
        """The Gaussian adapter on the depth predictor's outputs, in float32 whatever
        autocast says (the Gaussians' geometry, and the rasteriser takes float32 only)."""
        e = self.opacity_exponent(global_step)
        with torch.autocast(extrinsics.device.type, enabled=False):
            p = depth.densities.float()
            opacities = 0.5 * (1 - (1 - p) ** e + p ** (1 / e)) / self.cfg.gaussians_per_pixel
            gaussians, _ = self.gaussian_adapter(extrinsics, intrinsics,
                                                 depth.raw_gaussians.float(),
                                                 depth.depths.float(), opacities, image_shape)
        return gaussians

    def forward(self, images: Float[Tensor, "b v 3 h w"], extrinsics: Float[Tensor, "b v 4 4"],
                intrinsics: Float[Tensor, "b v 3 3"], near: Float[Tensor, "b v"],
                far: Float[Tensor, "b v"], global_step: int = 0) -> Gaussians:
        """Gaussians of the context views: images in [0, 1], extrinsics camera-to-world
        (OpenCV), intrinsics normalised, near/far per view."""
        _, _, depth = self.encode(images, extrinsics, intrinsics, near, far)
        depth.drop_intermediates()
        return self.gaussians_from(depth, extrinsics, intrinsics, tuple(images.shape[-2:]),
                                   global_step)
