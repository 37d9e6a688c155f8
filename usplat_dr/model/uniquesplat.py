"""UniqueSplat: the primary network (MVSplat's encoder) whose predictor layers take weights
W + Delta W from a view-agnostic and a view-specific hypernetwork, so that every target view
gets its own Gaussians.

The encoder (backbone, transformer, cost volume, U-Nets) runs once per scene; the target
layers and what follows them (the rest of their head, the Gaussian adapter) run per target,
all targets batched. Variants (the paper's ablation): ``baseline`` (a) the primary network;
``agnostic`` (b) target layers take W = H_a(e_a), the same for every view (cached when not
training); ``full`` (c) W + Delta W with Delta W = H_s(phi(Proj(E_H(context), P_t))).
"""

import dataclasses
import logging
from dataclasses import dataclass, field, fields, replace

import torch
from jaxtyping import Float
from torch import Tensor, nn

from usplat_dr.geometry.cameras import Cameras, baseline_scale
from usplat_dr.model.auto_budget import AutoBudget, Calibration, choose_keep, image_psnr
from usplat_dr.model.budget import (
    GaussianBudget,
    ImportanceHead,
    apply_budget,
    budget_count,
    dither_offsets,
)
from usplat_dr.model.checkpoint import check_state_dict, extract_state_dict, read_checkpoint
from usplat_dr.model.decoder import DecoderSplatting
from usplat_dr.model.encoder.depth_predictor import DepthOutputs
from usplat_dr.model.encoder.primary import (
    PrimaryNetwork,
    PrimaryNetworkCfg,
    check_bounds,
    check_finite,
    config_from_dict,
)
from usplat_dr.model.hypernet.hypernetwork import (
    AgnosticHypernetwork,
    ConvSpec,
    LayerDelta,
    SpecificHypernetwork,
)
from usplat_dr.model.hypernet.injection import adapter_layout, run_head, vb_layout
from usplat_dr.model.hypernet.view_branch import ViewSpecificEmbedding
from usplat_dr.model.predict import DEFAULT_FAR, DEFAULT_NEAR, Prediction, predict_views
from usplat_dr.model.types import Gaussians
from usplat_dr.render.prune import PruneSettings, footprint_scores

log = logging.getLogger(__name__)

#: The variants, each with its label in the paper's tables and our reports: (a) the primary
#: network alone, (b) with view-agnostic weights, (c) with view-specific ones as well.
VARIANTS = {"baseline": "(a) primary network", "agnostic": "(b) + view-agnostic",
            "full": "(c) UniqueSplat"}
HEADS = ("to_gaussians", "to_disparity")
#: Layers that can take generated weights: the convolutions of the two heads.
INJECTABLE = tuple(f"{h}.{i}" for h in HEADS for i in (0, 2))

#: Inference default: no pruning. Pruning pays nowhere on CPU (train/bench/prune.py, BENCHMARKS.md
#: "Pruning that pays"): the rasteriser's binning already skips what culling drops (no
#: (tile, Gaussian) pairs), so on the tiny checkpoint's Gaussians it saves the rasteriser 0-13 %
#: while the pruning itself costs 0.65-1.6x the render (64x64 to 256x256, one thread). Set
#: ``model.inference_prune = PruneSettings(...)`` for fewer Gaussians per view (culling is
#: exact; culling + merging within a pixel lost <= 0.005 dB in ``usplat bench``).
DEFAULT_INFERENCE_PRUNE: PruneSettings | None = None

# Paper sec. "Results reported": the full model has 38.1M parameters.
PAPER_PARAMETERS = 38.1e6

#: ``UniqueSplatCfg.gauge``'s values.
GAUGES = ("world", "baseline")


@dataclass(frozen=True)
class UniqueSplatCfg:
    """Everything that shapes a UniqueSplat model. See ``PRESETS`` for the named ones."""

    primary: PrimaryNetworkCfg = field(default_factory=PrimaryNetworkCfg)
    variant: str = "full"
    # Layers whose weights the hypernetworks generate: W (H_a) for all of them, and W + Delta W
    # (H_s) for ``specific_layers``. By default every convolution of the predictor's two heads,
    # as the paper has it ("integrated into the convolutional layers of the predictor" that
    # outputs centre, opacity, covariance and colour): ``to_disparity`` (depth, opacity) and
    # ``to_gaussians`` (colour, covariance, offsets). Fewer layers cost less per target
    # (``train/bench/uniquesplat.py --layers``; train/studies/LOG.md, "What view
    # conditioning costs").
    target_layers: tuple[str, ...] = INJECTABLE
    specific_layers: tuple[str, ...] = INJECTABLE
    embed_dim: int = 512  # e_a and e_s (paper: 512)
    hyper_hidden: int = 32  # width of the two hidden layers of H_a and H_s
    # width of H_s's hidden layers where it differs from H_a's (None: hyper_hidden)
    specific_hidden: int | None = None
    # Delta W as a rank-r product per layer (None: a full Delta W per view; see
    # hypernet/hypernetwork.py for the cost of each)
    delta_rank: int | None = 16
    # Standard deviation of the initial weights of H_s's last layer that make U (0: Delta W
    # is exactly 0 and (c) starts exactly at (a); > 0: it starts close to (a) and the
    # view-specific branch gets gradients from the first step; docs/learning.md)
    delta_init_std: float = 0.0
    # E_H: "resnet18" (the paper: a ResNet18 on the context images) or "primary" (the
    # primary network's backbone features, which it trained to match across views; read,
    # never trained through: docs/model.md, "Is the branch live?")
    view_features: str = "resnet18"
    resnet_stages: int = 4  # ResNet18 stages used by E_H (4: all of it)
    resnet_weights: str | None = None  # torchvision resnet18 .pth file (ImageNet)
    feature_dim: int = 64  # channels of F_c
    proj_samples: int = 32  # samples per target ray
    proj_stride: int = 8  # target grid of Proj = image size / proj_stride
    proj_temperature: float = 10.0  # initial softmax temperature over the samples
    phi_channels: tuple[int, ...] = (128, 256, 256, 256)
    # A Gaussian budget chosen at inference (model/budget.py, docs/model.md): an importance
    # head on the Gaussian head's input (one logit per Gaussian) and the adaptation of the kept
    # Gaussians to the budget. Off: the model, its checkpoints and MVSplat's load as before.
    importance: bool = False
    importance_hidden: int = 32  # width of the importance head and of the adaptation MLP
    # The unit the network works in. "world": the cameras' own (MVSplat's: its cost volume,
    # depth head and camera embeddings read absolute translations and inverse depths, so a
    # prediction depends on the unit a capture was posed in). "baseline": every example is
    # divided by the distance between its first and last context cameras (translations and
    # near/far), the network runs there and its Gaussians are scaled back, so the prediction
    # is the same whatever unit the cameras come in (pixelSplat's make_baseline_1 with its
    # bounds scaled, inside the model so that training, evaluation and users' photos share
    # it; docs/model.md, "The gauge").
    gauge: str = "world"

    def __post_init__(self):
        check_bounds(self, {"embed_dim": 8192, "hyper_hidden": 4096, "specific_hidden": 4096,
                            "delta_rank": 4096,
                            "resnet_stages": 4, "feature_dim": 2048, "proj_samples": 2048,
                            "proj_stride": 256, "phi_channels": 4096,
                            "importance_hidden": 4096})
        if self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {tuple(VARIANTS)}, got {self.variant!r}")
        bad = [t for t in self.target_layers if t not in INJECTABLE]
        if bad or not self.target_layers or len(set(self.target_layers)) != len(
                self.target_layers):
            raise ValueError(f"target_layers must be distinct names from {INJECTABLE}, got "
                             f"{self.target_layers}")
        if not self.specific_layers or not set(self.specific_layers) <= set(self.target_layers):
            raise ValueError(f"specific_layers must be a non-empty subset of target_layers "
                             f"{self.target_layers}, got {self.specific_layers}")
        for name in ("embed_dim", "hyper_hidden", "feature_dim", "proj_samples", "proj_stride",
                     "importance_hidden"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.gauge not in GAUGES:
            raise ValueError(f"gauge must be one of {GAUGES}, got {self.gauge!r}")
        if self.view_features not in ("resnet18", "primary"):
            raise ValueError(f"view_features must be 'resnet18' or 'primary', got "
                             f"{self.view_features!r}")
        if self.specific_hidden is not None and self.specific_hidden < 1:
            raise ValueError(f"specific_hidden must be >= 1 or None (H_a's width), got "
                             f"{self.specific_hidden}")
        if not self.delta_init_std >= 0:
            raise ValueError(f"delta_init_std must be >= 0, got {self.delta_init_std}")
        if self.delta_rank is not None and self.delta_rank < 1:
            raise ValueError(f"delta_rank must be >= 1 or None (full Delta W), got "
                             f"{self.delta_rank}")

    @classmethod
    def from_dict(cls, d: dict) -> "UniqueSplatCfg":
        """From plain values (YAML/JSON): ``primary`` a dict of ``PrimaryNetworkCfg`` fields."""
        d = dict(d)
        if isinstance(d.get("primary"), dict):
            d["primary"] = PrimaryNetworkCfg.from_dict(d["primary"])
        return config_from_dict(cls, d)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


PRESETS: dict[str, UniqueSplatCfg] = {
    # The paper's configuration: MVSplat's RE10K encoder, 512-d embeddings, a full ResNet18.
    "paper": UniqueSplatCfg(),
    # For CPU demos and tests at 64x64: a 4x smaller encoder, 2 ResNet stages.
    "tiny": UniqueSplatCfg(
        primary=PrimaryNetworkCfg(
            d_feature=32, num_transformer_layers=2, num_depth_candidates=32,
            costvolume_unet_feat_dim=32, costvolume_unet_attn_res=(4,),
            depth_unet_feat_dim=16, depth_unet_channel_mult=(1, 1, 1),
            depth_unet_attn_res=(4,), sh_degree=2),
        embed_dim=128, hyper_hidden=16, delta_rank=4, resnet_stages=2, feature_dim=32,
        proj_samples=16, phi_channels=(32, 32, 64, 64)),
    # Between the two (about 4x tiny): a 64-channel encoder with 4 transformer layers, three
    # ResNet stages. For `usplat bench`'s size axis.
    "small": UniqueSplatCfg(
        primary=PrimaryNetworkCfg(
            d_feature=64, num_transformer_layers=4, num_depth_candidates=64,
            costvolume_unet_feat_dim=64, costvolume_unet_attn_res=(4,),
            depth_unet_feat_dim=32, depth_unet_channel_mult=(1, 1, 1, 1),
            depth_unet_attn_res=(8,), sh_degree=3),
        embed_dim=256, hyper_hidden=32, delta_rank=8, resnet_stages=3, feature_dim=64,
        proj_samples=32, phi_channels=(64, 64, 128, 128)),
}


@dataclass
class UniqueSplatOutput:
    """``gaussians``: batch B N (target n of scene b at b N + n), each set for its own
    target view (for the baseline and agnostic variants the same set repeated).
    ``color`` [B, N, 3, H, W], ``alpha`` and ``depth`` [B, N, H, W] when rendered.
    ``aux``: ``embedding`` e_s [B, N, D] and Proj's ``correlation`` / ``weights`` (full
    variant); ``context_depths`` and ``context_coarse_depths`` [B, V, H, W] (the context
    views' predicted depth after and before refinement); ``kept`` [B, N] (the Gaussians each
    target kept: all of them unless a budget was given; ``rendered`` counts what pruning
    left) and, under a budget, ``importance`` and ``kept_mask`` [B*N, G] (the ranking scores
    and the top-K over the model's G Gaussians, in their order: view, pixel, Gaussian)."""

    gaussians: Gaussians
    num_targets: int
    per_target: bool
    color: Float[Tensor, "b n 3 h w"] | None = None
    alpha: Float[Tensor, "b n h w"] | None = None
    depth: Float[Tensor, "b n h w"] | None = None
    aux: dict = field(default_factory=dict)

    def target(self, b: int, n: int) -> Gaussians:
        """The Gaussians of target ``n`` of scene ``b``."""
        i = b * self.num_targets + n
        return Gaussians(**{f.name: getattr(self.gaussians, f.name)[i:i + 1]
                            for f in fields(Gaussians)})


class GeneratedConv(nn.Module):
    """Stands where a target convolution was: its weights come from the hypernetworks."""

    def __init__(self, spec: ConvSpec):
        super().__init__()
        self.spec = spec

    def forward(self, x):
        raise RuntimeError(f"{self.spec.name} takes generated weights; run it through "
                           f"UniqueSplat.forward")

    def extra_repr(self) -> str:
        return f"{self.spec}"


@dataclass(frozen=True)
class StudyHooks:
    """What studies that hold parts of the network fixed give ``forward`` (``hooks=``):
    ``encoding``, what ``UniqueSplat.encode`` returned for these context views, skips the
    encoder (its result must not need a gradient); ``delta_w`` (layer name -> ``LayerDelta``
    for B*N targets, layers of ``INJECTABLE``) replaces the view-specific branch's Delta W,
    in any variant."""

    encoding: DepthOutputs | None = None
    delta_w: dict | None = None


class UniqueSplat(nn.Module):
    """``UniqueSplat(config)`` or ``UniqueSplat.from_preset("paper" | "small" | "tiny",
    variant=...)``.

    ``forward(images, context, targets, *, render=True, ...) -> UniqueSplatOutput``: the
    order of ``SceneInputs``, the cameras as ``Cameras`` values following the field's
    conventions (camera-to-world OpenCV extrinsics, normalised intrinsics).
    """

    def __init__(self, config: UniqueSplatCfg | None = None):
        super().__init__()
        cfg = config or UniqueSplatCfg()
        self.cfg = cfg
        self.primary = PrimaryNetwork(cfg.primary)
        dp = self.primary.depth_predictor
        heads = {h: getattr(dp, h) for h in HEADS}
        self.specs = tuple(ConvSpec.of(t, heads[t.split(".")[0]][int(t.split(".")[1])])
                           for t in cfg.target_layers)
        self.specific_specs = tuple(s for s in self.specs if s.name in cfg.specific_layers)
        self._cached_weights = None
        #: Renders the predicted Gaussians (MVSplat's SH basis): ``render_targets``.
        self.decoder = DecoderSplatting()
        #: [min near, max near, min far, max far] of the scenes the loaded checkpoint trained
        #: on (``usplat_dr.training.loader.load`` sets it), ``None`` when unknown.
        self.trained_depth_range: list[float] | None = None
        #: Per-target pruning before rasterisation when not training (``forward``'s
        #: ``prune="auto"``); ``None`` renders every Gaussian. See ``usplat_dr.render.prune``.
        self.inference_prune = DEFAULT_INFERENCE_PRUNE
        #: Inference precision of the networks when not training: ``"float32"`` (default) or
        #: ``"bfloat16"`` (torch autocast; the Gaussians' geometry, the cost volume's
        #: sampling grid and rendering stay float32). On an AVX-512-BF16 CPU with native
        #: numerics (``USPLAT_PORTABLE=0``: the portable pins leave oneDNN without bfloat16
        #: instructions, 14x slower) it takes the paper preset's 256x256 encoder from 3.25 to
        #: 1.82 s at one thread and moved the tiny checkpoint's held-out PSNR by +0.013 dB
        #: (train/bench/README.md, "bfloat16 inference").
        self.inference_precision = "float32"
        #: The importance head and budget adaptation (``cfg.importance``; model/budget.py).
        self.importance = None
        if cfg.importance:
            p = cfg.primary
            self.importance = ImportanceHead(p.depth_unet_feat_dim + 3 + p.d_feature,
                                             cfg.importance_hidden, p.gaussians_per_pixel)
        self._warned_no_head = False
        #: The automatic count's calibrations by ranking (model/auto_budget.py), from the
        #: loaded checkpoint or its manifest entry; empty: the proxy uncalibrated.
        self.auto_calibration: dict[str, Calibration] = {}
        self._warned_auto: set[str] = set()  # the automatic count's warnings, once each
        self.agnostic = self.specific = None
        if cfg.variant == "baseline":
            return
        base = torch.cat([t.reshape(-1) for s in self.specs
                          for t in (self._conv(s.name).weight, self._conv(s.name).bias)])
        self.agnostic = AgnosticHypernetwork(self.specs, cfg.embed_dim, cfg.hyper_hidden,
                                             base.detach())
        for s in self.specs:  # the hypernetworks own these weights now
            head, i = s.name.split(".")
            heads[head][int(i)] = GeneratedConv(s)
        if cfg.variant == "full":
            primary_channels = (dp.proj_feature.in_channels if cfg.view_features == "primary"
                                else None)
            self.view_embedding = ViewSpecificEmbedding(
                cfg.resnet_stages, cfg.feature_dim, cfg.proj_samples, cfg.proj_temperature,
                cfg.proj_stride, cfg.phi_channels, cfg.embed_dim, primary_channels)
            self.specific = SpecificHypernetwork(self.specific_specs, cfg.embed_dim,
                                                 cfg.specific_hidden or cfg.hyper_hidden,
                                                 cfg.delta_rank,
                                                 cfg.delta_init_std)
            if cfg.view_features == "resnet18":
                self.view_embedding.features.resnet.load_torchvision(cfg.resnet_weights)

    # ---- construction -------------------------------------------------------------------

    @classmethod
    def from_preset(cls, name: str = "paper", variant: str = "full", **overrides
                    ) -> "UniqueSplat":
        """A named configuration (``PRESETS``: "paper", "small", "tiny") and variant ("baseline",
        "agnostic", "full"); ``overrides`` replace other ``UniqueSplatCfg`` fields."""
        if name not in PRESETS:
            raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {name!r}")
        return cls(replace(PRESETS[name], variant=variant, **overrides))

    def conv_spec(self, name: str) -> ConvSpec:
        """The shape of head convolution ``name`` (one of ``INJECTABLE``), whatever owns
        its weights."""
        if name not in INJECTABLE:
            raise ValueError(f"name must be one of {list(INJECTABLE)}, got {name!r}")
        conv = self._conv(name)
        return conv.spec if isinstance(conv, GeneratedConv) else ConvSpec.of(name, conv)

    def _conv(self, name: str) -> nn.Conv2d:
        head, i = name.split(".")
        return getattr(self.primary.depth_predictor, head)[int(i)]

    def load_mvsplat(self, checkpoint, map_location="cpu", trust_checkpoint: bool = False
                     ) -> "UniqueSplat":
        """Load an MVSplat checkpoint (path, Lightning dict or bare state dict) into the
        primary network strictly; for the agnostic and full variants the target layers'
        weights become W (H_a's output bias, with zero last-layer weight), so that the
        untrained model renders what MVSplat renders."""
        sd = extract_state_dict(read_checkpoint(checkpoint, map_location, trust_checkpoint))
        if self.agnostic is not None:
            keys = {f"depth_predictor.{s.name}.{p}": shape for s in self.specs
                    for p, shape in (("weight", s.weight_shape), ("bias", (s.out_channels,)))}
            check_state_dict({**self.primary.state_dict(), **keys}, sd)
            base = torch.cat([sd.pop(k).reshape(-1) for k in keys])
            self.agnostic.set_base(base.to(self.agnostic.hyper.last.bias))
        check_state_dict(self.primary, sd)
        self.primary.load_state_dict(sd, strict=True)
        self._cached_weights = None
        return self

    # ---- the weights of the target layers ----------------------------------------------

    def agnostic_weights(self) -> list[tuple[Tensor, Tensor]]:
        """W per target layer (weight, bias). Cached while not training and gradients are
        off; the cache is dropped when H_a's parameters change (in-place version counters)."""
        if self.agnostic is None:
            return [(self._conv(s.name).weight, self._conv(s.name).bias) for s in self.specs]
        params = tuple(self.agnostic.parameters())
        key = tuple((id(p), p._version) for p in params)
        # W in float32 whatever autocast says (the cache must not keep a bfloat16 W for a
        # later float32 forward; autocast casts it where a convolution uses it).
        with torch.autocast(params[0].device.type, enabled=False):
            if self.training or torch.is_grad_enabled():
                self._cached_weights = None
                return self.agnostic()
            if self._cached_weights is None or self._cached_weights[0] != key:
                self._cached_weights = (key, self.agnostic())
        return self._cached_weights[1]

    def train(self, mode: bool = True):
        self._cached_weights = None
        return super().train(mode)

    # ---- forward ------------------------------------------------------------------------

    def check_targets(self, b: int, targets: Cameras) -> int:
        """N, the targets per example, once ``targets`` are B examples' finite cameras of
        the right shapes with 0 < near < far (else a ``ValueError`` naming the field)."""
        target_extrinsics, target_intrinsics, target_near, target_far = (
            targets.extrinsics, targets.intrinsics, targets.near, targets.far)
        if target_intrinsics.ndim != 4 or target_intrinsics.shape[0] != b:
            raise ValueError(f"target_intrinsics must have shape [B={b}, N, 3, 3], got "
                             f"{list(target_intrinsics.shape)}")
        n = target_intrinsics.shape[1]
        if n < 1:
            raise ValueError("target_intrinsics must hold >= 1 target view")
        for name, t, shape in (("target_extrinsics", target_extrinsics, (b, n, 4, 4)),
                               ("target_intrinsics", target_intrinsics, (b, n, 3, 3)),
                               ("target_near", target_near, (b, n)),
                               ("target_far", target_far, (b, n))):
            if tuple(t.shape) != shape:
                raise ValueError(f"{name} must have shape {list(shape)}, got {list(t.shape)}")
        check_finite(target_extrinsics=target_extrinsics, target_intrinsics=target_intrinsics,
                     target_near=target_near, target_far=target_far)
        if (target_near <= 0).any() or (target_far <= target_near).any():
            raise ValueError("target_near must be > 0 and target_far > target_near")
        return n

    def forward(self, images: Float[Tensor, "b v 3 h w"], context: Cameras, targets: Cameras,
                *, render: bool = True, global_step: int = 0,
                background_color: Tensor | None = None, settings=None, prune="auto",
                budget: GaussianBudget | AutoBudget | None = None,
                hooks: StudyHooks | None = None) -> UniqueSplatOutput:
        """Gaussians per target view, and their renders (``render=True``) through the
        Dr.Jit rasteriser with MVSplat's SH basis (``settings``: a ``RasterSettings``).
        ``context``: the ``Cameras`` of the V context ``images``; ``targets``: the N target
        cameras (``model(*model_inputs(batch))`` passes all three).

        ``prune``: a ``PruneSettings`` applied per target before rasterising, ``None`` for
        none, or ``"auto"``: none while training, ``self.inference_prune`` otherwise. The
        number of Gaussians each target rendered is ``out.aux["rendered"]`` [B, N].

        ``budget`` (a ``GaussianBudget``, model/budget.py): keep K Gaussians per target, ranked
        as it says. ``out.aux["kept"]`` [B, N]: the Gaussians each target kept; with a budget
        also ``importance`` (the ranking scores) and ``kept_mask`` [B*N, G]. ``budget=None``
        (or a fraction of 1) leaves every output as without it, bit for bit. An ``AutoBudget``
        (model/auto_budget.py; inference, one scene a call) chooses the scene's budget from
        renders of its context views: ``out.aux["auto_keep"]`` [B] the fraction chosen,
        ``auto_readings`` what it measured, ``auto_budget`` and ``auto_prune`` the budget and
        pruning chosen, ``auto_total`` the Gaussians per target it chose from; with its
        ``merge`` the targets render with near-duplicates merged.

        ``hooks`` (``StudyHooks``): for studies that hold parts of the network fixed."""
        if budget is not None and not isinstance(budget, (GaussianBudget, AutoBudget)):
            raise ValueError(f"budget must be a GaussianBudget (e.g. GaussianBudget(0.3)), an "
                             f"AutoBudget or None, got {budget!r}")
        hooks = hooks or StudyHooks()
        encoding, delta_w = hooks.encoding, hooks.delta_w
        scale = self.gauge_scale(context.extrinsics)  # None in the world gauge
        world_context, world_targets = context, targets
        if scale is not None:  # the network runs in the gauge, the Gaussians come back
            context, targets = context.scaled(1.0 / scale), targets.scaled(1.0 / scale)
        if isinstance(prune, str) and prune != "auto":
            raise ValueError(f"prune must be a PruneSettings, None or 'auto', got {prune!r}")
        if prune == "auto":
            prune = None if self.training else self.inference_prune
        b, v, _, h, w = images.shape
        n = self.check_targets(b, targets)
        with self._autocast(images.device):
            if encoding is None:
                depth = self._encode(images, context)
            else:
                depth = self._check_encoding(encoding, b, v, h, w)
            if delta_w is None:
                weights, deltas, aux = self._target_weights(images, context, targets, depth)
            else:
                weights = dict(zip(self.cfg.target_layers, self.agnostic_weights()))
                deltas, aux = self._check_delta_w(delta_w, b * n), {}
            nb = n if deltas else 1  # per-target work only where Delta W exists
            depth_out = self._run_heads(depth, weights, deltas, context, v, b, nb)
        gaussians = self._gaussians_per_target(depth_out, context, (h, w), global_step, b, n,
                                               nb)
        context, targets = world_context, world_targets
        if scale is not None:
            gaussians = gaussians.scaled(scale.repeat_interleave(n))
        kept = len(gaussians)
        if isinstance(budget, AutoBudget):
            budget, prune = self._auto_budget(budget, images, context, depth, hooks, prune, aux)
            aux["auto_total"] = kept  # the Gaussians per target the count chose from
        if budget is not None:
            gaussians, kept = self._budgeted(gaussians, depth, aux, targets, (h, w), v, b, n,
                                             budget)
        aux["kept"] = torch.full((b, n), kept, device=images.device)
        # The context views' depth maps [B, V, H, W] (the first target's where they differ
        # per target; MVSplat's depth: the distance along the pixel's unit ray, not z): what
        # a depth loss supervises. ``context_coarse_depths`` is the
        # cost volume's estimate before refinement; unlike the final depths it is never
        # clamped to [near, far], so it keeps a gradient where the final depth saturates.
        aux["context_depths"] = depth_out.depths.view(b, nb, v, h, w, -1)[:, 0, ..., 0].float()
        coarse_disparity = depth.disp_full.float().view(v, b, h, w).transpose(0, 1)
        aux["context_coarse_depths"] = 1.0 / coarse_disparity
        if scale is not None:  # back in the cameras' unit
            for key in ("context_depths", "context_coarse_depths"):
                aux[key] = aux[key] * scale.float()[:, None, None, None]
        out = UniqueSplatOutput(gaussians=gaussians, num_targets=n, per_target=bool(deltas),
                                aux=aux)
        if render:
            self.render_targets(out, targets, (h, w), background_color, settings, prune)
        return out

    def _auto_budget(self, auto: AutoBudget, images: Tensor, context: Cameras,
                     depth: DepthOutputs, hooks: StudyHooks, prune, aux: dict
                     ) -> tuple[GaussianBudget | None, PruneSettings | None]:
        """``forward``'s automatic count (model/auto_budget.py): the budget it chose for this
        scene (``None``: every Gaussian) and the pruning the targets render with; ``aux``
        gets ``auto_keep``, ``auto_readings``, ``auto_budget`` and ``auto_prune``."""
        if self.training:
            raise ValueError("budget=AutoBudget(...) chooses a count at inference: call "
                             "model.eval() first (training takes a GaussianBudget)")
        if images.shape[0] != 1:
            raise ValueError(f"budget=AutoBudget(...) chooses a count per scene: pass one scene "
                             f"a call (batch size 1), got {images.shape[0]}")
        if hooks.delta_w is not None:
            raise ValueError("budget=AutoBudget(...) renders the context views as targets, "
                             "which hooks.delta_w (sized for the targets) cannot serve")
        rank_by = auto.rank_by or "dither"  # the better one at the budgets a count keeps
        calibration = auto.calibration or self.auto_calibration.get(rank_by)
        if calibration is not None and calibration.rank_by != rank_by:
            raise ValueError(f"AutoBudget.calibration was measured with rank_by="
                             f"{calibration.rank_by!r}, not {rank_by!r}: pass that ranking or "
                             f"a calibration of this one")
        if calibration is None and f"none {rank_by}" not in self._warned_auto:
            self._warned_auto.add(f"none {rank_by}")
            log.warning("no calibration of the automatic count for this model and rank_by=%r: "
                        "the context views' own loss is the prediction, which overstates the "
                        "targets' and keeps more Gaussians than needed; make one with "
                        "train/studies/auto_budget_proxy.py (docs/model.md)", rank_by)
        size = min(images.shape[-2:])
        if (calibration is not None and calibration.size not in (None, size)
                and f"size {rank_by}" not in self._warned_auto):
            self._warned_auto.add(f"size {rank_by}")
            log.warning("the automatic count's calibration (rank_by=%r) was measured at %d "
                        "pixels a side, these images are %d: its prediction may be off; "
                        "calibrate at this size (docs/model.md)", rank_by, calibration.size, size)
        # The context views as targets: their Gaussians predicted once (the heads do not
        # depend on the budget), then each budget selected from them and rendered.
        v, (h, w) = images.shape[1], images.shape[-2:]
        with torch.no_grad():
            own = self.forward(images, context, context, hooks=StudyHooks(encoding=depth),
                               render=False)

        def context_psnr(budget: GaussianBudget | None) -> float:
            with torch.no_grad():
                gaussians, aux_k = own.gaussians, {}
                if budget is not None:
                    gaussians, _ = self._budgeted(gaussians, depth, aux_k, context, (h, w), v,
                                                  1, v, budget)
                out = UniqueSplatOutput(gaussians=gaussians, num_targets=v,
                                        per_target=own.per_target, aux=aux_k)
                self.render_targets(out, context, (h, w), prune=self.inference_prune)
            return float(image_psnr(out.color, images).mean())

        reference = context_psnr(None)
        keep, readings = choose_keep(
            lambda k: reference - context_psnr(GaussianBudget(k, rank_by)), auto, calibration)
        if auto.merge and (prune is None or not prune.merge):
            prune = replace(prune or PruneSettings(), merge=True)
        chosen = None if keep >= 1.0 else GaussianBudget(keep, rank_by)
        # what another call on this scene (more targets) passes to render as this one does
        aux.update(auto_keep=torch.tensor([keep], dtype=torch.float64, device=images.device),
                   auto_readings=[readings], auto_budget=chosen, auto_prune=prune)
        return chosen, prune

    def _budgeted(self, gaussians: Gaussians, depth: DepthOutputs, aux: dict, targets: Cameras,
                  image_shape: tuple[int, int], v: int, b: int, n: int,
                  budget: GaussianBudget) -> tuple[Gaussians, int]:
        """``forward``'s budget: the kept Gaussians and K (model/budget.py); ``aux`` gets the
        scores and the kept mask (and, while training, the unbudgeted Gaussians). ``targets``
        and ``image_shape``: the target views, for the ``"footprint"`` ranking."""
        device = gaussians.means.device
        rank_by = budget.rank_by
        if rank_by is None:
            rank_by = "learned" if self.importance is not None else "dither"
            # (once per model: a command's every forward would repeat it)
            if self.importance is None and not self._warned_no_head:
                self._warned_no_head = True
                log.warning("this model has no importance head: the Gaussian budget keeps "
                            "Gaussians by ordered dithering of their opacity and rescales them "
                            "by the coverage rule (rank_by='dither', the learned ranking's "
                            "untrained start); fine-tune the head with usplat train --config "
                            "synthetic_tiny_budget.yaml (docs/model.md)")
        if rank_by == "learned" and self.importance is None:
            raise ValueError("rank_by='learned' needs a model with an importance head "
                             "(UniqueSplatCfg.importance=True, fine-tuned by usplat train "
                             "--config synthetic_tiny_budget.yaml); use rank_by='dither', "
                             "'opacity' or 'random'")
        if budget_count(budget.keep, len(gaussians)) >= len(gaussians):
            return gaussians, len(gaussians)  # everything kept: nothing computed, nothing changed
        logits = features = dither = footprint = None
        if rank_by == "footprint":  # one set per target: [B*N, G]
            footprint = footprint_scores(
                targets.extrinsics.flatten(0, 1), targets.intrinsics.flatten(0, 1),
                targets.near.flatten(0, 1), image_shape, gaussians.means.float(),
                gaussians.covariances.float(), gaussians.opacities.float())
        if rank_by == "learned":
            with self._autocast(device):
                logits, features = self.importance(depth.head_input, v, b)  # [B, G], [B, G, F]
            # one density per scene, repeated for its targets: [B*N, G]
            logits = logits.repeat_interleave(n, 0)
            features = features.repeat_interleave(n, 0)
        h, w = depth.disp_full.shape[-2:]
        layout = (v, h, w, self.cfg.primary.gaussians_per_pixel)
        if rank_by in ("learned", "dither"):
            dither = dither_offsets(*layout, device=device)
        chosen = apply_budget(gaussians, budget.keep, rank_by, logits, features,
                              self.importance, dither, layout, budget.tau, budget.seed,
                              footprint)
        if chosen.scores is not None:
            aux.update(importance=chosen.scores, kept_mask=chosen.kept_mask)
            if chosen.mask is not None:
                aux["budget_mask"] = chosen.mask
            if self.training:  # for a loss on the full render beside the budgeted one
                aux["unbudgeted"] = gaussians
        return chosen.gaussians, chosen.kept

    def gauge_scale(self, extrinsics: Float[Tensor, "b v 4 4"]) -> Tensor | None:
        """The length, in the cameras' unit, of one unit of the gauge the network works in
        (``UniqueSplatCfg.gauge``), per example; ``None`` in the world gauge."""
        if self.cfg.gauge == "world":
            return None
        return baseline_scale(extrinsics)

    def encode(self, images: Float[Tensor, "b v 3 h w"], extrinsics: Float[Tensor, "b v 4 4"],
               intrinsics: Float[Tensor, "b v 3 3"], near: Float[Tensor, "b v"],
               far: Float[Tensor, "b v"]) -> DepthOutputs:
        """The primary network up to its heads (backbone, transformer, cost volume, U-Nets):
        what ``forward`` computes once per scene, reusable as its ``encoding`` (in the
        model's gauge; the cameras are given in their own unit)."""
        context = Cameras(extrinsics, intrinsics, near, far)
        scale = self.gauge_scale(extrinsics)
        if scale is not None:
            context = context.scaled(1.0 / scale)
        return self._encode(images, context)

    def _encode(self, images, context: Cameras) -> DepthOutputs:
        return self.primary.encode(images, context.extrinsics, context.intrinsics, context.near,
                                   context.far, run_heads=False)[2]

    @staticmethod
    def _check_encoding(encoding, b: int, v: int, h: int, w: int) -> DepthOutputs:
        if not isinstance(encoding, DepthOutputs) or encoding.head_input is None:
            raise ValueError("encoding must be what UniqueSplat.encode returned for these "
                             "context views (a DepthOutputs with its head inputs)")
        if tuple(encoding.disp_full.shape) != (v * b, 1, h, w):
            raise ValueError(f"encoding is for other context views: its disparity has shape "
                             f"{list(encoding.disp_full.shape)}, these views need "
                             f"{[v * b, 1, h, w]}")
        if encoding.head_input.requires_grad or encoding.refine_out.requires_grad:
            raise ValueError("encoding needs a gradient: a reused encoding would backpropagate "
                             "into its graph twice; compute it under torch.no_grad()")
        return encoding

    @staticmethod
    def _check_delta_w(delta_w: dict, rows: int) -> dict:
        if not isinstance(delta_w, dict) or not set(delta_w) <= set(INJECTABLE):
            raise ValueError(f"delta_w must map layer names of {list(INJECTABLE)} to "
                             f"LayerDelta, got keys {list(delta_w)}")
        for name, d in delta_w.items():
            if not isinstance(d, LayerDelta) or d.bias.shape[0] != rows:
                raise ValueError(f"delta_w[{name!r}] must be a LayerDelta for B*N = {rows} "
                                 f"targets")
        return delta_w

    def _autocast(self, device: torch.device):
        """bfloat16 autocast for the networks when ``inference_precision`` asks for it and
        the model is not training; otherwise nothing changes."""
        if self.inference_precision not in ("float32", "bfloat16"):
            raise ValueError(f"inference_precision must be 'float32' or 'bfloat16', got "
                             f"{self.inference_precision!r}")
        enabled = self.inference_precision == "bfloat16" and not self.training
        return torch.autocast(device.type, dtype=torch.bfloat16, enabled=enabled)

    def view_delta_w(self, images: Float[Tensor, "b v 3 h w"],
                     extrinsics: Float[Tensor, "b v 4 4"], intrinsics: Float[Tensor, "b v 3 3"],
                     target_extrinsics: Float[Tensor, "b n 4 4"],
                     target_intrinsics: Float[Tensor, "b n 3 3"],
                     target_near: Float[Tensor, "b n"], target_far: Float[Tensor, "b n"],
                     near: Float[Tensor, "b v"] | None = None,
                     far: Float[Tensor, "b v"] | None = None,
                     encoding: DepthOutputs | None = None) -> dict[str, LayerDelta]:
        """The view-specific branch's Delta W for each target (layer name -> ``LayerDelta``
        for B*N targets, target n of scene b at b N + n), what ``forward`` adds to W; ``{}``
        for a model without the branch. ``forward(hooks=StudyHooks(delta_w=...))`` takes it
        back (edited, or as ``usplat_dr.evaluation.view_specificity`` does, averaged over a
        scene's targets).
        With ``view_features="primary"`` E_H reads the encoder's features: ``encoding``
        (``encode``'s), or the context ``near``/``far`` to compute it."""
        if self.specific is None:
            return {}
        targets = Cameras(target_extrinsics, target_intrinsics, target_near, target_far)
        self.check_targets(images.shape[0], targets)
        if self.cfg.view_features == "primary" and encoding is None:
            if near is None or far is None:
                raise ValueError("near and far (or encoding) are needed: this model's E_H "
                                 "reads the primary network's features")
            encoding = self.encode(images, extrinsics, intrinsics, near, far)
        # the branch reads the context cameras' poses, not their near/far: where none are
        # given, any positive pair stands in
        bounds = (near, far) if near is not None and far is not None else (
            extrinsics.new_ones(extrinsics.shape[:2]), extrinsics.new_full(extrinsics.shape[:2], 2))
        context = Cameras(extrinsics, intrinsics, *bounds)
        scale = self.gauge_scale(extrinsics)
        if scale is not None:  # the branch reads the cameras in the network's gauge
            context, targets = context.scaled(1.0 / scale), targets.scaled(1.0 / scale)
        return self._target_weights(images, context, targets, encoding)[1]

    def generated_weights(self) -> dict[str, tuple[Tensor, Tensor]]:
        """W, the view-agnostic weights of the target layers: layer name -> (weight, bias)
        (the head's own convolutions for the baseline)."""
        return dict(zip(self.cfg.target_layers, self.agnostic_weights()))

    def _target_weights(self, images: Float[Tensor, "b v 3 h w"], context: Cameras,
                        targets: Cameras, depth: DepthOutputs | None = None
                        ) -> tuple[dict, dict, dict]:
        """The generated layers' weights: ``W`` (layer -> (weight, bias)) from the
        view-agnostic branch, ``Delta W`` (layer -> per-target low-rank factors) from the
        view-specific branch, and the branch's diagnostics (embedding, Proj's correlation
        and weights) for ``out.aux``. Either dict is empty where its branch is absent."""
        aux, deltas = {}, {}
        if self.specific is not None:
            features = None
            if self.cfg.view_features == "primary":  # the encoder's, (v b) -> [B, V, ...]
                f = depth.features_fullres
                b, v = images.shape[:2]
                features = f.reshape(v, b, *f.shape[1:]).transpose(0, 1)
            e_s, proj_aux = self.view_embedding(images, context.extrinsics, context.intrinsics,
                                                targets.extrinsics, targets.intrinsics,
                                                targets.near, targets.far, features)
            aux.update(embedding=e_s, correlation=proj_aux["correlation"],
                       weights=proj_aux["weights"])
            deltas = {s.name: d for s, d in zip(self.specific_specs,
                                                self.specific(e_s.flatten(0, 1)))}
        weights = dict(zip(self.cfg.target_layers, self.agnostic_weights()))
        return weights, deltas, aux

    def _run_heads(self, depth, weights: dict, deltas: dict, context: Cameras, v: int, b: int,
                   nb: int):
        """The depth predictor's two heads (``to_gaussians``, ``to_disparity``) with the
        generated weights, for ``nb`` target batches (1: the same for every target), and
        the depths they give: ``depth`` (the encoder's ``DepthOutputs``) with its raw
        Gaussians, depths and densities replaced, laid out [(B nb), V, ...]."""
        dp = self.primary.depth_predictor

        def head(name: str, x: Tensor):
            layers = []
            for i in (0, 2):
                key = f"{name}.{i}"
                if key in weights:
                    wt, bias = weights[key]
                else:
                    conv = getattr(dp, name)[i]
                    wt, bias = conv.weight, conv.bias
                layers.append((wt, bias, deltas.get(key)))
            return run_head(x, layers, v, b, nb)

        raw, pt = head("to_gaussians", depth.head_input)
        raw = adapter_layout(raw, pt, v, b, nb)  # [(B nb), V, HW, C]
        disp, pt = head("to_disparity", depth.refine_out)
        # scene-level tensors repeated per target batch entry
        near_t, far_t = (context.near.repeat_interleave(nb, 0),
                         context.far.repeat_interleave(nb, 0))
        disp_full = vb_layout(depth.disp_full, False, v, b, nb)
        depths, densities = dp.depths_from(vb_layout(disp, pt, v, b, nb), disp_full,
                                           near_t, far_t)
        return dataclasses.replace(depth, raw_gaussians=raw, depths=depths,
                                   densities=densities)

    def _gaussians_per_target(self, depth_out, context: Cameras, image_shape: tuple[int, int],
                              global_step: int, b: int, n: int, nb: int) -> Gaussians:
        """Gaussians [(B N), G, ...] from the heads' outputs: one set per target batch
        entry, expanded to every target where they do not depend on it (``nb == 1``)."""
        ext_t = context.extrinsics.repeat_interleave(nb, 0)
        int_t = context.intrinsics.repeat_interleave(nb, 0)
        gaussians = self.primary.gaussians_from(depth_out, ext_t, int_t, image_shape,
                                                global_step)
        if nb == 1 and n > 1:  # the same Gaussians for every target
            gaussians = Gaussians(**{
                f.name: getattr(gaussians, f.name)[:, None].expand(
                    b, n, *getattr(gaussians, f.name).shape[1:]).flatten(0, 1)
                for f in fields(Gaussians)})
        return gaussians

    def render_targets(self, out: UniqueSplatOutput, targets: Cameras,
                       image_shape: tuple[int, int], background_color=None, settings=None,
                       prune=None) -> None:
        """Render ``out``'s Gaussians for its ``targets`` at ``image_shape`` (any size: the
        intrinsics are normalised) into ``out.color/alpha/depth`` and ``out.aux["rendered"]``
        with the model's decoder (``self.decoder``, ``usplat_dr.model.decoder``; another
        ``settings`` renders through one made for them); ``forward(render=True)`` calls it
        at the context images' size. ``prune``: a ``PruneSettings`` or ``None``."""
        decoder = self.decoder if settings is None else DecoderSplatting(settings)
        r = decoder.forward(out.gaussians, targets.extrinsics, targets.intrinsics, targets.near,
                            targets.far, image_shape, background_color, prune)
        out.color, out.alpha, out.depth = r.color, r.alpha, r.depth
        out.aux["rendered"] = r.rendered

    def predict(self, images, *, intrinsics, extrinsics, target_intrinsics, target_extrinsics,
                near=DEFAULT_NEAR, far=DEFAULT_FAR, chunk: int = 8,
                budget: float | int | str | GaussianBudget | AutoBudget | None = None,  # noqa: PYI041
                rank_by: str | None = None, all_gaussians: bool = True,
                tolerance: float | int | None = None) -> Prediction:  # noqa: PYI041
        """Novel views from a user's own images: the Gaussians, colour and depth of each
        target camera (a ``Prediction``), predicted in evaluation mode without gradients.

        ``images``: V >= 2 context images, uint8 (0-255) or float in [0, 1], [V, H, W, 3] or
        [V, 3, H, W] (numpy, torch or a list; H and W multiples of the preset's
        ``image_multiple``); ``intrinsics`` [V, 3, 3] normalised (fx/W, fy/H, cx/W, cy/H);
        ``extrinsics`` [V, 4, 4] camera-to-world, OpenCV axes; ``target_*`` the same for N
        targets (one camera may come without its leading axis); ``near``/``far`` the depth
        range in scene units (a number, or one per context view; the default is MVSplat's
        RE10K range); ``chunk`` targets per forward pass. Cameras are keyword-only.
        ``budget``: keep K Gaussians per target (a count, or a fraction in (0, 1]) ranked by
        ``rank_by``, as in ``forward``; each ``gaussians[n]`` then holds K. ``budget="auto"``:
        the scene's own K, the smallest whose loss is predicted within ``tolerance`` dB
        (default 0.2; model/auto_budget.py), ``Prediction.auto_keep`` the fraction chosen; the
        targets then render with near-duplicates merged.
        ``all_gaussians=False``: ``gaussians`` holds the first target's only (a long camera
        path then holds ``chunk`` targets' Gaussians at a time)."""
        return predict_views(self, images, intrinsics=intrinsics, extrinsics=extrinsics,
                             target_intrinsics=target_intrinsics,
                             target_extrinsics=target_extrinsics, near=near, far=far,
                             chunk=chunk, budget=budget, rank_by=rank_by,
                             all_gaussians=all_gaussians, tolerance=tolerance)

    # ---- reporting ----------------------------------------------------------------------

    def parameter_table(self) -> list[tuple[str, int]]:
        """(part, parameter count) rows; the last row is the total."""
        def count(m):
            return sum(p.numel() for p in m.parameters()) if m is not None else 0

        dp = self.primary.depth_predictor
        rows = [("primary: backbone (CNN + transformer)", count(self.primary.backbone)),
                ("primary: depth predictor (without generated layers)", count(dp))]
        if self.agnostic is not None:
            rows.append(("view-agnostic: e_a + H_a (W incl. its bias = base weights)",
                         count(self.agnostic)))
        if self.importance is not None:
            rows.append(("budget: importance head + adaptation", count(self.importance)))
        if self.specific is not None:
            ve = self.view_embedding
            if self.cfg.view_features == "resnet18":
                e_h = f"view-specific: E_H ResNet18 ({self.cfg.resnet_stages} stages, no fc)"
                rows.append((e_h, count(ve.features.resnet)))
            else:
                rows.append(("view-specific: E_H the primary's features (no weights)", 0))
            rows += [("view-specific: lateral convs + Proj temperature",
                      count(ve.features.lateral) + count(ve.proj)),
                     ("view-specific: phi", count(ve.phi)),
                     ("view-specific: H_s", count(self.specific))]
        rows.append(("total", sum(p.numel() for p in self.parameters())))
        return rows
