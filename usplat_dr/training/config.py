"""The typed training configuration: one dataclass per section of the YAML configs, whose
defaults are the field's recipe (MVSplat / pixelSplat: Adam, peak lr 2e-4 on a one-cycle cosine
schedule, gradient clipping at 0.5, MSE + 0.05 LPIPS after step 150,000, 300,000 steps). These
defaults are the only ones: ``usplat_dr/configs/base.yaml`` documents them and sets nothing.

``RootCfg.load(cfg)`` checks a loaded config (``usplat_dr.config.load_config``): an unknown key,
a value of the wrong type or out of range (``RANGES``) is a ``ConfigError`` naming the key and
the file or command-line override that set it. The ``dataset`` section is
``usplat_dr.data.dataset.DatasetSectionCfg`` (its view sampler chosen by
``dataset.view_sampler.name``), loaded and checked the same way, once.
"""

import dataclasses
import math
import os
from dataclasses import dataclass, field

from usplat_dr.config import ConfigError, load_typed, where_set
from usplat_dr.data.dataset import DatasetSectionCfg
from usplat_dr.data.view_sampler import ViewSamplerBoundedCfg
from usplat_dr.model import UniqueSplat
from usplat_dr.model.uniquesplat import PRESETS, UniqueSplatCfg
from usplat_dr.training.checkpoints import init_from_checkpoint


@dataclass(frozen=True)
class TrainCfg:
    """The ``train`` section: length and cadence of a run."""

    steps: int = 300_000  # optimiser steps (the field's recipe)
    checkpoint_every: int = 1000  # steps between checkpoints (also at the end and on signals)
    # > 0: a checkpoint saved at a multiple of this many steps is also kept as
    # checkpoints/step_<step>.ckpt (a curve of checkpoints to evaluate); 0: only last.ckpt
    keep_every: int = 0
    validate_every: int = 5000  # steps between validation renders
    log_every: int = 10  # steps between rows of metrics.csv
    max_nonfinite: int = 20  # non-finite steps in a row that stop the run
    progress: bool = True  # a progress bar
    # A Gaussian budget per step (docs/model.md, "A Gaussian budget chosen at inference"):
    # fractions of the Gaussians the budgeted render keeps; empty: none, every step renders
    # them all. Needs the importance head (model.overrides.importance: true).
    budget_fractions: tuple[float, ...] = ()
    # "choice": one of budget_fractions per step; "log_uniform": log(fraction) uniform between
    # their smallest and largest (every budget in between at inference, not only the listed)
    budget_sampling: str = "choice"
    # temperature of the relaxed top-K mask (model/budget.py, in logits), geometric from the
    # first value at step 0 to the second at the last step: soft early (every Gaussian near the
    # threshold gets a gradient), close to the hard top-K of inference at the end
    budget_tau: tuple[float, float] = (1.0, 0.05)
    # "all": every parameter trains; "budget": only the importance head and the adaptation
    # (the rest frozen: the unbudgeted model stays the checkpoint's, bit for bit, and a step
    # backpropagates through the rasteriser and the head only); "view_specific": only the
    # view-specific branch (E_H, Proj, phi, H_s), the primary network and H_a frozen: can the
    # branch learn to vary with the view at all? (docs/model.md, "Is the branch live?")
    trainable: str = "all"


@dataclass(frozen=True)
class OptimizerCfg:
    """The ``optimizer`` section: Adam on a one-cycle cosine schedule."""

    lr: float = 2e-4  # peak of the one-cycle cosine schedule
    warm_up_fraction: float = 0.01
    gradient_clip: float = 0.5  # global norm
    hyper_lr_scale: float = 1.0  # learning rate of the hypernetwork branches over lr (1: one rate)


@dataclass(frozen=True)
class LossCfg:
    """The ``loss`` section: MSE, LPIPS after a step, optional depth supervision."""

    mse: float = 1.0
    lpips: float = 0.05
    lpips_after_step: int = 150_000  # the paper: LPIPS joins after 150k steps
    lpips_vgg: str | None = None  # torchvision vgg16-397923af.pth (needed once LPIPS is on)
    lpips_lin: str | None = None  # lpips/weights/v0.1/vgg.pth from the lpips pip package
    depth: float = 0.0  # weight of the log-depth L1 on the context views (docs/learning.md)
    # weight of the log-depth L1 on the rendered target views' depth (alpha > 0.5 pixels)
    target_depth: float = 0.0
    depth_until_step: int | None = None  # the depth terms end here (None: never)
    # weight of the MSE of the unbudgeted render beside the budgeted one, in steps with a
    # budget (train.budget_fractions; with train.trainable=all: keeps the full model's quality)
    full_render: float = 0.0


@dataclass(frozen=True)
class DataLoaderCfg:
    """The ``data_loader`` section (torch's DataLoader)."""

    batch_size: int = 1
    num_workers: int = 0


@dataclass(frozen=True)
class ModelSection:
    """The ``model`` section: which UniqueSplat, and the weights it starts from."""

    preset: str = "tiny"  # usplat_dr.model.uniquesplat.PRESETS
    variant: str = "full"  # baseline (a), agnostic (b), full (c)
    overrides: dict = field(default_factory=dict)  # fields of the preset's UniqueSplatCfg
    init_mvsplat: str | None = None  # an MVSplat checkpoint for the primary network
    init_from: str | None = None  # a usplat checkpoint of (a): the paper's protocol
    # unpickle init_mvsplat / init_from (and, with --resume, the run's last.ckpt) fully, for
    # files that torch.load(weights_only=True) refuses; only for files you trust (runs code)
    trust_checkpoint: bool = False
    # > 0: after the weights are loaded, add N(0, std^2) noise (the run's seed) to the weights
    # of H_s's last-layer rows that make U and the bias deltas, which every view-specific
    # gradient is proportional to (zero-initialised, they leave the branch without one;
    # SpecificHypernetwork.open_gate). Needs the full variant.
    open_gate_std: float = 0.0


#: ``train.trainable``'s choices: which parameters a run trains.
TRAINABLE = ("all", "budget", "view_specific")


def _positive_finite(x: float) -> bool:
    return math.isfinite(x) and x > 0


#: The ranges ``RootCfg.load`` checks: dotted key -> (test, what the message says).
RANGES = {
    # (10^9 steps is years of any machine: a larger count is a typo, e.g. 10**30)
    "train.steps": (lambda v: 1 <= v <= 10**9, "must be >= 1 and <= 1,000,000,000"),
    "output_dir": (lambda v: bool(str(v).strip()), "must name a folder (it is empty)"),
    "train.checkpoint_every": (lambda v: v >= 1, "must be >= 1"),
    "train.keep_every": (lambda v: v >= 0, "must be >= 0 (0: keep only last.ckpt)"),
    "train.validate_every": (lambda v: v >= 1, "must be >= 1"),
    "train.log_every": (lambda v: v >= 1, "must be >= 1"),
    "train.max_nonfinite": (lambda v: v >= 1, "must be >= 1"),
    "optimizer.lr": (_positive_finite, "must be finite and > 0"),
    "optimizer.warm_up_fraction": (lambda v: 0 <= v < 1, "must be in [0, 1)"),
    "optimizer.gradient_clip": (lambda v: v > 0, "must be > 0 (.inf: no clipping)"),
    "optimizer.hyper_lr_scale": (_positive_finite, "must be finite and > 0"),
    "loss.mse": (lambda v: math.isfinite(v) and v >= 0, "must be finite and >= 0"),
    "loss.lpips": (lambda v: math.isfinite(v) and v >= 0, "must be finite and >= 0"),
    "loss.depth": (lambda v: math.isfinite(v) and v >= 0, "must be finite and >= 0"),
    "loss.target_depth": (lambda v: math.isfinite(v) and v >= 0, "must be finite and >= 0"),
    "loss.full_render": (lambda v: math.isfinite(v) and v >= 0, "must be finite and >= 0"),
    "train.budget_fractions": (lambda v: all(0 < f <= 1 for f in v),
                               "must be fractions in (0, 1] (or empty: no budget)"),
    "train.budget_sampling": (lambda v: v in ("choice", "log_uniform"),
                              "must be choice or log_uniform"),
    "train.budget_tau": (lambda v: all(_positive_finite(t) for t in v),
                         "must be two temperatures, finite and > 0"),
    "train.trainable": (lambda v: v in TRAINABLE, f"must be one of {', '.join(TRAINABLE)}"),
    "model.open_gate_std": (lambda v: math.isfinite(v) and v >= 0, "must be finite and >= 0"),
    # more threads than CPUs only time-slice them (and torch/OpenMP would start them all)
    "threads": (lambda v: v is None or 1 <= v <= (os.cpu_count() or 1),
                (f"must be >= 1 and at most this machine's CPUs (os.cpu_count() = "
                 f"{os.cpu_count()}); or null: one per free core (USPLAT_THREADS), or cores / "
                 f"ranks under torchrun")),
    "data_loader.batch_size": (lambda v: v >= 1, "must be >= 1"),
    "data_loader.num_workers": (lambda v: v >= 0, "must be >= 0"),
    "keep_cores_awake": (lambda v: v in (True, False, None, "auto"), "must be true, false or auto"),
}


#: The bounded view sampler's ranges (``dataset.view_sampler.*``): field -> (test, what the
#: message says, formatted with the sampler's config as ``c``). Negative views or gaps fail
#: inside the data loader's workers (torch.randint), zero target views make an empty loss
#: (NaN), a minimum above its maximum no example at all.
SAMPLER_RANGES = {
    "num_context_views": (lambda c: c.num_context_views == 2,
                          "must be 2 (the bounded sampler picks two context views)"),
    "num_target_views": (lambda c: c.num_target_views >= 1, "must be >= 1"),
    "min_distance_between_context_views": (
        lambda c: 0 <= c.min_distance_between_context_views
        <= c.max_distance_between_context_views,
        ("must be >= 0 and <= max_distance_between_context_views "
         "({c.max_distance_between_context_views})")),
    "initial_min_distance_between_context_views": (
        lambda c: 0 <= c.initial_min_distance_between_context_views
        <= c.initial_max_distance_between_context_views,
        ("must be >= 0 and <= initial_max_distance_between_context_views "
         "({c.initial_max_distance_between_context_views})")),
    "min_distance_to_context_views": (lambda c: c.min_distance_to_context_views >= 0,
                                      "must be >= 0"),
    "warm_up_steps": (lambda c: c.warm_up_steps >= 0, "must be >= 0 (0: no warm-up)"),
    "max_distance_beyond_context_views": (
        lambda c: c.max_distance_beyond_context_views >= 0 and not (
            c.max_distance_beyond_context_views and c.min_distance_to_context_views),
        ("must be >= 0 (0: targets between the context views only), and 0 while "
         "min_distance_to_context_views ({c.min_distance_to_context_views}) is set")),
}


def check_sampler_ranges(sampler: object, origins: dict) -> None:
    """A ``ConfigError`` naming the first ``SAMPLER_RANGES`` value of a bounded sampler's
    config that is out of range and where it was set; other samplers pass."""
    if not isinstance(sampler, ViewSamplerBoundedCfg):
        return
    for name, (ok, requirement) in SAMPLER_RANGES.items():
        if not ok(sampler):
            key = f"dataset.view_sampler.{name}"
            raise ConfigError(f"{key}={getattr(sampler, name)!r} is out of range (set in "
                              f"{where_set(origins, key)}): {requirement.format(c=sampler)}")


@dataclass(frozen=True)
class RootCfg:
    """A whole training configuration (the YAML file's top level)."""

    seed: int = 0
    device: str = "cpu"  # cuda: torch on the GPU and the rasteriser on Dr.Jit's CUDA backend
    output_dir: str = "outputs/train"
    # torch and Dr.Jit threads per process (None: one per core that other processes leave free,
    # usplat_dr._threads; cores / ranks under torchrun)
    threads: int | None = None
    # idle-priority spinners that keep the cores from halting between the run's threads
    # (usplat_dr.training.cores); auto (or null): on for a CPU run whose threads cover all of
    # its cores on a VM whose idle cores a probe at start finds slow to wake
    keep_cores_awake: bool | str | None = "auto"
    # float32 convolutions and matrix products on a GPU: null keeps torch's defaults (cuDNN
    # convolutions in TF32, matrix products in IEEE float32); false: IEEE float32 for both
    # (slower, closer to the CPU's numbers); true: TF32 for both. No effect on the CPU.
    tf32: bool | None = None
    name: str | None = None  # a label for the run
    model: ModelSection = field(default_factory=ModelSection)
    dataset: DatasetSectionCfg = field(default_factory=DatasetSectionCfg)
    data_loader: DataLoaderCfg = field(default_factory=DataLoaderCfg)
    optimizer: OptimizerCfg = field(default_factory=OptimizerCfg)
    loss: LossCfg = field(default_factory=LossCfg)
    train: TrainCfg = field(default_factory=TrainCfg)

    @classmethod
    def load(cls, cfg: dict) -> "RootCfg":
        """The typed configuration of a loaded config (its ``origins`` name the files), its
        values checked for range (a ``ConfigError`` names the key and where it was set)."""
        root = load_typed(cls, cfg)
        origins = getattr(cfg, "origins", {}) or {}
        for key, (ok, requirement) in RANGES.items():
            value = root
            for part in key.split("."):
                value = getattr(value, part)
            if not ok(value):
                raise ConfigError(f"{key}={value!r} is out of range (set in "
                                  f"{where_set(origins, key)}): {requirement}")
        check_sampler_ranges(root.dataset.view_sampler, origins)
        tc = root.train
        if tc.keep_every % tc.checkpoint_every:
            raise ConfigError(f"train.keep_every={tc.keep_every} is not a multiple of "
                              f"train.checkpoint_every={tc.checkpoint_every} (set in "
                              f"{where_set(origins, 'train.keep_every')}): checkpoints are "
                              f"kept where one is saved; make it a multiple, or 0")
        return root


def model_from_config(section: ModelSection | dict) -> UniqueSplat:
    """The model a config's ``model`` section describes: a preset, a variant, overrides of the
    preset's fields, and weights to start from (``init_mvsplat``: an MVSplat checkpoint;
    ``init_from``: a usplat checkpoint of (a), the paper's protocol)."""
    if not isinstance(section, ModelSection):
        section = load_typed(ModelSection, section, "model")
    if section.preset not in PRESETS:
        raise ConfigError(f"model.preset must be one of {sorted(PRESETS)}, got "
                          f"{section.preset!r}")
    base = dataclasses.asdict(PRESETS[section.preset])
    over = dict(section.overrides)
    if "primary" in over:
        base["primary"] = {**base["primary"], **over.pop("primary")}
    model = UniqueSplat(UniqueSplatCfg.from_dict({**base, **over, "variant": section.variant}))
    if section.init_mvsplat and section.init_from:
        raise ConfigError("model.init_mvsplat and model.init_from both set: choose one")
    if section.init_mvsplat:
        model.load_mvsplat(section.init_mvsplat, trust_checkpoint=section.trust_checkpoint)
    if section.init_from:
        init_from_checkpoint(model, section.init_from, trust=section.trust_checkpoint)
    if section.open_gate_std > 0:
        if model.specific is None:
            raise ConfigError(f"model.open_gate_std={section.open_gate_std} needs the "
                              f"view-specific branch: model.variant=full, got "
                              f"{section.variant!r}")
        model.specific.open_gate(section.open_gate_std, weight=1.0)
    return model
