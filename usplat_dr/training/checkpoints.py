"""Checkpoint files of training: a model from one (``load_model``), the primary network of a
trained (a) as the start of (b) and (c) (``init_from_checkpoint``), a shippable copy of one
(``export_weights``), and the registry of the shipped ones (``CHECKPOINTS``, its
``manifest.json`` read by ``shipped_checkpoints``, its ``verdict.json`` by
``registered_verdict``)."""

import contextlib
import dataclasses
import json
import logging
import os
from pathlib import Path

import numpy as np
import torch

from usplat_dr.config import ConfigError
from usplat_dr.data.chunks import MAX_IMAGE_PIXELS
from usplat_dr.io import load_torch_file, torch_save
from usplat_dr.io.user_files import sha256
from usplat_dr.model import UniqueSplat, UniqueSplatCfg
from usplat_dr.model.auto_budget import Calibration
from usplat_dr.model.budget import RANKINGS
from usplat_dr.model.checkpoint import check_state_dict
from usplat_dr.training.registry import (  # noqa: F401  (the loader's names, here too)
    CHECKPOINTS,
    resolve_checkpoint,
    shipped_checkpoints,
)

#: How a user opts in to full unpickling (named in the refusal's message).
TRUST_HINT = "--trust-checkpoint (usplat eval/render/export-ply/train) or trust=True"

log = logging.getLogger(__name__)


def read_usplat_checkpoint(checkpoint: str | os.PathLike, map_location="cpu",
                           trust: bool = False, cache: bool = True) -> dict:
    """A usplat checkpoint file as a dict, loaded with ``torch.load(weights_only=True)``:
    ours hold tensors and plain data only. ``trust=True`` allows full unpickling (files
    written before RNG states were stored as plain data need it; it can run code). The last
    few files read are kept (``READ_CACHE``, keyed by the file's path, size and modification
    time): a command that asks a file its size, its depth range and then its model reads it
    once. Each call returns its own top-level dict; the tensors are shared, read-only by
    convention (``load_state_dict`` copies them). ``cache=False``: read and keep nothing (a
    training state, read once to resume)."""
    path = Path(checkpoint)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {str(path)!r} does not exist (usplat train writes "
                                f"OUTPUT_DIR/checkpoints/last.ckpt; shipped ones are in "
                                f"checkpoints/)")
    state = _load(path, map_location, trust, cache)
    if "base" in state:
        state = _on_base(path, state, map_location, trust, cache)
    return state


#: How many checkpoint files ``read_usplat_checkpoint`` keeps (a command reads one or two
#: models, an add-on its base beside it).
READ_CACHE = 3
_READ: dict[tuple, dict] = {}
_SHA256: dict[tuple, str] = {}


def _stat_key(path: Path, *more) -> tuple:
    stat = path.stat()
    return (str(path.resolve()), stat.st_ino, stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns,
            *more)


def _load(path: Path, map_location, trust: bool, cache: bool = True) -> dict:
    """One file's dict as ``torch.load`` gives it (an add-on not yet completed), kept in
    ``_READ`` unless ``cache=False``; a copy of its top level each call."""
    key = _stat_key(path, str(map_location), trust)
    if cache and key in _READ:
        return dict(_READ[key])
    state = load_torch_file(path, "checkpoint", map_location, trust=trust,
                            trust_hint=TRUST_HINT)
    if not isinstance(state, dict):
        raise ValueError(f"checkpoint {str(path)!r} holds a {type(state).__name__}, not a "
                         f"usplat checkpoint (a dict with 'model' and 'model_config')")
    # kept: weights files read on the CPU (the shipped ones are megabytes); never a training
    # state with its optimiser, nor a copy on a GPU beside the model's own weights
    if cache and str(map_location) == "cpu" and "optimizer" not in state:
        _READ[key] = state
        while len(_READ) > READ_CACHE:
            _READ.pop(next(iter(_READ)))
    return dict(state)


#: Bytes a checkpoint file may hold (the paper preset's MVSplat checkpoint is about 150 MB).
MAX_CHECKPOINT_BYTES = 4 * 2**30


def _file_sha256(path: Path) -> str:
    """A checkpoint file's sha256, computed once per file version in a process."""
    key = _stat_key(path)
    if key not in _SHA256:
        _SHA256[key] = sha256(path, "checkpoint", MAX_CHECKPOINT_BYTES)
    return _SHA256[key]


def _on_base(path: Path, state: dict, map_location, trust: bool, cache: bool = True) -> dict:
    """An add-on checkpoint (``export_weights(..., base=)``) completed: it holds only the
    weights that differ from a base checkpoint's (the budget stage's importance head on a
    shipped model: kilobytes instead of a copy of the model), and names the base by file name
    and sha256. The base is looked for beside the add-on, then among the shipped checkpoints,
    and must be byte for byte the one the add-on was made on."""
    base = state["base"]
    if not (isinstance(base, dict) and isinstance(base.get("file"), str)
            and isinstance(base.get("sha256"), str)):
        raise ValueError(f"checkpoint {str(path)!r}: its 'base' must be {{'file': NAME, "
                         f"'sha256': HEX}} (written by export_weights(..., base=))")
    name = base["file"]
    # a file name, never a path: a crafted file could otherwise name any file of the machine
    if Path(name).name != name or name in (".", "..") or not name.endswith(".pt"):
        raise ValueError(f"checkpoint {str(path)!r}: its base {name!r} is not a .pt file name")
    found = next((p for p in (path.parent / name, CHECKPOINTS / name) if p.is_file()), None)
    if found is None:
        raise FileNotFoundError(f"checkpoint {str(path)!r} holds only the weights it adds to "
                                f"{name}; put {name} (usplat-dr's checkpoints/) beside it")
    try:
        found_sha256 = _file_sha256(found)
    except ValueError as e:  # a damaged base: named with the add-on the user asked for
        raise ValueError(f"checkpoint {str(path)!r} (an add-on): its base: {e}") from None
    if found_sha256 != base["sha256"]:
        raise ValueError(f"checkpoint {str(path)!r} was made on a {name} with sha256 "
                         f"{base['sha256'][:12]}..., and {found} is another file (a newer "
                         f"release?): use the {name} it was made on")
    base_state = _load(found, map_location, trust, cache)
    if "base" in base_state:
        raise ValueError(f"checkpoint {str(path)!r}: its base {found} is not a complete usplat "
                         f"checkpoint (an add-on's base holds every weight)")
    own, inherited = state.get("model"), base_state.get("model")
    if not isinstance(own, dict) or not isinstance(inherited, dict):
        raise ValueError(f"checkpoint {str(path)!r} or its base {found}: 'model' is not a "
                         f"state dict (names -> tensors)")
    unused = base.get("unused", [])
    if not (isinstance(unused, list) and all(isinstance(k, str) for k in unused)):
        raise ValueError(f"checkpoint {str(path)!r}: its base's 'unused' must be a list of "
                         f"weight names (written by export_weights(..., base=))")
    unused = set(unused)
    inherited = {k: v for k, v in inherited.items() if k not in unused}
    return {**state, "model": {**inherited, **own}}


@contextlib.contextmanager
def _quiet_resnet():
    """No "ResNet18 weights not found" warning: the weights come from the checkpoint."""
    resnet_log = logging.getLogger("usplat_dr.model.hypernet.resnet")
    level = resnet_log.level
    resnet_log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        resnet_log.setLevel(level)


#: The dtypes a checkpoint's tensors may have (float16 shipped, float32 trained; integer
#: buffers such as BatchNorm's count).
LOADABLE_DTYPES = (torch.float16, torch.bfloat16, torch.float32, torch.float64, torch.int64,
                   torch.int32, torch.uint8, torch.bool)


def foreign_tensor(weights: dict[str, torch.Tensor]) -> str | None:
    """What is wrong with the first tensor of ``weights`` that is not dense, of a
    ``LOADABLE_DTYPES`` dtype, on the CPU or a GPU (a sparse, meta, quantised or float8 tensor
    of the right shape fails later in some op with torch's message, or is cast silently by
    ``load_state_dict``), else ``None``.

    Examples:
        >>> foreign_tensor({"w": torch.zeros(2)}) is None
        True
        >>> foreign_tensor({"w": torch.zeros(2).to(torch.float8_e4m3fn)})
        'w is a torch.strided torch.float8_e4m3fn tensor on cpu'
    """
    for name, value in weights.items():
        if (value.layout != torch.strided or value.device.type not in ("cpu", "cuda")
                or value.is_quantized or value.dtype not in LOADABLE_DTYPES):
            return f"{name} is a {value.layout} {value.dtype} tensor on {value.device.type}"
    return None


def _model_state(path: Path, state: dict) -> tuple[UniqueSplatCfg, dict[str, torch.Tensor]]:
    """The model config and weights of a loaded usplat checkpoint, checked against each other
    without building the network: a ``ValueError`` naming ``path`` unless ``model_config``
    describes a UniqueSplat whose parameters and buffers have exactly the shapes of
    ``model``'s tensors, floating where the network's are, and finite.

    The config's ``resnet_weights`` is cleared: a path stored in a checkpoint is never opened
    (it named a file of the machine that trained, and a crafted one could name any file or a
    FIFO); the ResNet18's weights are in ``model``."""
    if not isinstance(state.get("model_config"), dict):
        raise ValueError(f"{path} is not a usplat training checkpoint (no 'model_config'); "
                         f"an MVSplat checkpoint loads with UniqueSplat.load_mvsplat")
    sd = state.get("model")
    if not isinstance(sd, dict) or not all(
            isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in sd.items()):
        raise ValueError(f"{path}: 'model' is not a state dict (names -> tensors)")
    try:
        cfg = UniqueSplatCfg.from_dict(state["model_config"])
        cfg = dataclasses.replace(cfg, resnet_weights=None)
        # Built on the meta device (shapes, no memory) first: a corrupt model_config can ask
        # for any size (d_feature=10**6 makes 8e13 weights), so the real network is built
        # only once its shapes are those of the checkpoint's tensors, already in memory.
        with torch.device("meta"), _quiet_resnet():
            expected = UniqueSplat(cfg).state_dict()
    except (TypeError, ValueError, KeyError, RuntimeError) as e:  # RuntimeError: sizes overflow
        raise ValueError(f"{path}: its model_config does not describe a UniqueSplat "
                         f"({type(e).__name__}: {str(e)[:300]})") from None
    check_state_dict(expected, sd, what=f"checkpoint {path}")
    foreign = foreign_tensor(sd)
    if foreign:
        raise ValueError(f"{path}: {foreign}: a checkpoint holds dense float or integer "
                         f"tensors (a damaged or foreign file)")
    for name, value in sd.items():
        if value.is_complex() or value.is_floating_point() != expected[name].is_floating_point():
            raise ValueError(f"{path}: {name} is {value.dtype}, the network's is "
                             f"{expected[name].dtype}")
        if value.is_floating_point() and not torch.isfinite(value).all():
            raise ValueError(f"{path}: {name} holds {int((~torch.isfinite(value)).sum())} "
                             f"non-finite values (a corrupt file, or saved from a diverged run)")
    return cfg, sd


def load_model(checkpoint: str | os.PathLike, device: torch.device | str = "cpu",
               trust: bool = False):
    """A ``UniqueSplat`` from a training checkpoint (``usplat train``'s ``last.ckpt``) or a
    shipped one, and its step. ``trust``: see ``read_usplat_checkpoint``. A file that is not
    such a checkpoint, or whose weights do not fit its ``model_config``, is a ``ValueError``
    naming it."""
    path = Path(checkpoint)
    return _built(path, read_usplat_checkpoint(path, device, trust), device)


def _built(path: Path, state: dict, device) -> tuple[UniqueSplat, int]:
    """The model and step of a loaded usplat checkpoint ``state`` read from ``path``."""
    cfg, sd = _model_state(path, state)
    with _quiet_resnet():
        model = UniqueSplat(cfg)
    model.load_state_dict(sd)
    model.trained_depth_range = _depth_range(path, state)
    model.auto_calibration = _auto_calibration(path, state)
    step = state.get("step", 0)
    return model.to(device).eval(), step if isinstance(step, int) else 0


def checkpoint_provenance(checkpoint: str | os.PathLike, trust: bool = False) -> dict:
    """A usplat checkpoint's provenance record (``{}`` when it has none): the data hashes,
    libraries and, since ``train_keys`` was added, the training scenes' keys."""
    record = read_usplat_checkpoint(resolve_checkpoint(checkpoint), trust=trust).get(
        "provenance")
    return record if isinstance(record, dict) else {}


def training_image_shape(checkpoint: str | os.PathLike, trust: bool = False
                         ) -> tuple[int, int] | None:
    """The (H, W) a usplat checkpoint (a file or a shipped name) was trained at (its config's
    ``dataset.image_shape``), or ``None`` when the checkpoint does not record one (MVSplat's
    do not)."""
    state = read_usplat_checkpoint(resolve_checkpoint(checkpoint), trust=trust)
    if is_mvsplat_checkpoint(state):
        return None
    config = state.get("config") or {}
    dataset = (config.get("dataset") or {}) if isinstance(config, dict) else None
    if not isinstance(dataset, dict):
        raise ValueError(f"checkpoint {str(checkpoint)!r}: its 'config' is not a training "
                         f"config (a mapping with a 'dataset' mapping); pass --image-shape H W")
    shape = dataset.get("image_shape")
    if not shape:
        return None
    if (not isinstance(shape, (list, tuple)) or len(shape) != 2
            or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 1 for n in shape)
            or shape[0] * shape[1] > MAX_IMAGE_PIXELS):
        raise ValueError(f"checkpoint {str(checkpoint)!r}: its config's dataset.image_shape "
                         f"must be [H, W] (at most {MAX_IMAGE_PIXELS:,} pixels), got "
                         f"{shape!r}; pass --image-shape H W")
    return int(shape[0]), int(shape[1])


def training_depth_range(checkpoint: str | os.PathLike, trust: bool = False
                         ) -> list[float] | None:
    """[min near, max near, min far, max far] of the scenes a usplat checkpoint (a file or a
    shipped name) was trained on: the file's ``depth_range`` (``usplat train`` records it), else
    a shipped file's manifest entry, else ``None`` (older files, MVSplat's). ``load`` keeps it
    as the model's ``trained_depth_range``."""
    path = resolve_checkpoint(checkpoint)
    return _depth_range(path, read_usplat_checkpoint(path, trust=trust))


def _depth_range(path: Path, state: dict) -> list[float] | None:
    """``training_depth_range`` of the checkpoint ``state`` read from ``path``."""
    found = _recorded(path, state, "depth_range")
    if found is None:
        return None
    if (not isinstance(found, (list, tuple)) or len(found) != 4
            or not all(isinstance(x, (int, float)) and 0 < x < float("inf") for x in found)):
        raise ValueError(f"checkpoint {str(path)!r}: its depth_range must be four positive "
                         f"numbers [min near, max near, min far, max far], got {found!r}")
    return [float(x) for x in found]


def _recorded(path: Path, state: dict, key: str):
    """``key`` of a checkpoint ``state`` read from ``path``: the file's own value, else a
    shipped file's manifest entry's, else ``None``."""
    found = state.get(key)
    if found is None and path.parent.resolve() == CHECKPOINTS.resolve():
        entries = json.loads((CHECKPOINTS / "manifest.json").read_text())
        found = next((e.get(key) for e in entries if e.get("file") == path.name), None)
    return found


def _auto_calibration(path: Path, state: dict) -> dict[str, Calibration]:
    """The automatic count's calibrations ({rank_by: Calibration}) of the checkpoint
    ``state`` read from ``path``: the file's ``auto_budget`` (a list of
    ``Calibration.as_dict()``), else a shipped file's manifest entry's, else none."""
    found = _recorded(path, state, "auto_budget")
    if found is None:
        return {}
    if not isinstance(found, list):
        raise ValueError(f"checkpoint {str(path)!r}: its auto_budget must be a list of "
                         f"calibrations, got {type(found).__name__}")
    if len(found) > len(RANKINGS):
        raise ValueError(f"checkpoint {str(path)!r}: its auto_budget holds {len(found)} "
                         f"calibrations, more than one per ranking ({len(RANKINGS)})")
    where = f"checkpoint {str(path)!r}: auto_budget"
    if not all(isinstance(d, dict) for d in found):
        raise ValueError(f"{where}: not an automatic count's calibration (each entry a dict: "
                         f"rank_by, quantile, data, fits)")
    calibrations = [Calibration.from_dict(d, where) for d in found]
    ranks = [c.rank_by for c in calibrations]
    if len(set(ranks)) != len(ranks):
        raise ValueError(f"checkpoint {str(path)!r}: its auto_budget has two calibrations "
                         f"for one ranking ({ranks}): keep one per ranking")
    return {c.rank_by: c for c in calibrations}


def widened_depth_range(depth_range: list[float] | None, near: torch.Tensor,
                        far: torch.Tensor) -> list[float]:
    """``depth_range`` ([min near, max near, min far, max far], or ``None``) widened to hold
    a batch's ``near`` and ``far`` (any shape).

    Examples:
        >>> widened_depth_range(None, torch.tensor([[1.0, 2.0]]), torch.tensor([[50.0, 9.0]]))
        [1.0, 2.0, 9.0, 50.0]
        >>> widened_depth_range([1.0, 2.0, 9.0, 50.0], torch.tensor([0.5]), torch.tensor([20.0]))
        [0.5, 2.0, 9.0, 50.0]
        >>> widened_depth_range(None, torch.tensor([0.2]), torch.tensor([4.525]))  # float32
        [0.2, 0.2, 4.525, 4.525]
    """
    values = torch.stack([near.min(), near.max(), far.min(), far.max()])
    now = values.double().tolist()
    if values.dtype == torch.float32:  # the shortest decimal naming each float32 value: 0.2,
        now = [float(str(np.float32(v))) for v in now]  # not 0.20000000298023224
    if depth_range is None:
        return now
    return [min(depth_range[0], now[0]), max(depth_range[1], now[1]),
            min(depth_range[2], now[2]), max(depth_range[3], now[3])]


#: How far outside a checkpoint's training depth range a scene's near/far may lie before
#: ``depth_range_warning`` speaks: a factor of 2 either way. A choice, not a measured edge: it
#: stays quiet for every scene kind the shipped checkpoints trained on and speaks for a scene
#: in other units (millimetres, kilometres), where the loss is not small.
DEPTH_RANGE_SLACK = 2.0


def depth_range_warning(near: float, far: float, trained: list[float] | None) -> str | None:
    """A warning when ``near``/``far`` lie more than ``DEPTH_RANGE_SLACK`` times outside the
    ``trained`` range ([min near, max near, min far, max far], ``training_depth_range``), else
    ``None``.

    Examples:
        >>> depth_range_warning(0.5, 20.0, [0.2, 2.125, 4.525, 100.0]) is None
        True
        >>> depth_range_warning(0.01, 20.0, [0.2, 2.125, 4.525, 100.0])[:23]
        'near/far 0.01 / 20 lies'
    """
    if trained is None:
        return None
    lo_near, hi_near, lo_far, hi_far = trained
    k = DEPTH_RANGE_SLACK
    if lo_near / k <= near <= hi_near * k and lo_far / k <= far <= hi_far * k:
        return None
    return (f"near/far {near:.4g} / {far:.4g} lies far outside the checkpoint's training range "
            f"(near {lo_near:.4g}-{hi_near:.4g}, far {lo_far:.4g}-{hi_far:.4g}): expect a "
            f"worse render (near/far in docs/data.md)")


def load_models(runs: dict, device) -> dict:
    """``{key: model}`` from ``{key: run folder}`` (each run's ``checkpoints/last.ckpt``)."""
    return {key: load_model(run / "checkpoints" / "last.ckpt", device)[0]
            for key, run in runs.items()}


def init_from_checkpoint(model, path: str | os.PathLike, trust: bool = False) -> None:
    """The paper's protocol: the primary network (encoder and predictor) from a trained
    usplat checkpoint (``usplat train``'s or a shipped one, by path or name, any variant);
    for (b) and (c) its target layers' weights become W, and the hypernetworks'
    zero-initialised outputs make the model start exactly where that checkpoint is. The
    budget stage: a model with an importance head (``importance=True``) whose config is
    otherwise the checkpoint's (any variant, e.g. the shipped (c)) takes all of its weights,
    the new head starting at zero (``_load_adding_importance``). ``trust``: see
    ``read_usplat_checkpoint`` (``model.trust_checkpoint``)."""
    path = Path(path)
    if not path.is_file():  # a shipped model's name (full-64, study/tiny_full, an old one)
        with contextlib.suppress(FileNotFoundError):
            path = resolve_checkpoint(path)
    if not path.is_file():
        raise ConfigError(f"model.init_from: checkpoint {str(path)!r} does not exist")
    state = read_usplat_checkpoint(path, trust=trust)
    if "model_config" not in state:
        raise ConfigError(f"model.init_from: {path} is not a usplat checkpoint (no "
                          f"'model_config'); an MVSplat checkpoint goes in model.init_mvsplat")
    try:
        cfg, sd = _model_state(path, state)
    except ValueError as e:
        raise ConfigError(f"model.init_from: {e}") from None
    if model.cfg.importance and (_config_without(cfg, BUDGET_FIELDS)
                                 == _config_without(model.cfg, BUDGET_FIELDS)):
        _load_adding_importance(model, path, cfg, sd)
        return
    if cfg.variant == model.cfg.variant != "baseline" and (
            cfg.importance == model.cfg.importance) and (
            _config_without(cfg, BRANCH_FIELDS) == _config_without(model.cfg, BRANCH_FIELDS)):
        # the same (b) or (c) (e.g. the shipped (c), to train its view-specific branch further:
        # train.trainable=view_specific: every weight), or a (c) whose branch is configured
        # otherwise
        fresh = _load_matching(model, path, sd)
        if model.cfg.delta_init_std > 0 and not any(k.startswith("specific.") for k in fresh):
            log.warning("model.init_from: %s replaces H_s's initialisation, so delta_init_std "
                        "has no effect; model.open_gate_std adds noise after loading", path)
        return
    if cfg.variant != "baseline":
        raise ConfigError(f"model.init_from: {path} holds variant {cfg.variant!r} with another "
                          f"configuration than this model's; start from a baseline (a) "
                          f"checkpoint (its primary network is complete), or from one of this "
                          f"very model (same variant and overrides; with "
                          f"model.overrides.importance=true, the budget stage)")
    primary = {k.removeprefix("primary."): v.float() for k, v in sd.items()
               if k.startswith("primary.")}
    model.load_mvsplat(primary)


#: The fields a checkpoint may differ in from a model that starts from it with or without
#: the importance head (``_load_adding_importance``); the ResNet18 file is the training
#: machine's, its weights are in the checkpoint; the gauge changes the unit the network reads
#: its cameras in, none of its weights (a world-gauge model fine-tuned in the baseline gauge).
BUDGET_FIELDS = ("importance", "importance_hidden", "resnet_weights", "gauge")
#: ... and with another view-specific branch (``_load_matching``).
BRANCH_FIELDS = (*BUDGET_FIELDS, "specific_hidden", "view_features", "delta_rank",
                 "delta_init_std", "resnet_stages", "feature_dim", "proj_samples",
                 "proj_stride", "proj_temperature", "phi_channels", "specific_layers")


def _config_without(cfg: UniqueSplatCfg, fields: tuple[str, ...]) -> dict:
    """A model config's fields but ``fields``."""
    d = cfg.to_dict()
    for key in fields:
        d.pop(key)
    return d


def _load_matching(model, path: Path, sd: dict) -> list[str]:
    """``model`` from a checkpoint of its variant whose view-specific branch may be configured
    otherwise (a design change of the branch, measured from a trained (c)): every weight whose
    name and shape match, which is all of them outside the branch (the primary network, H_a);
    the branch's others keep their initialisation (logged). Returns those."""
    own = model.state_dict()
    take = {k: v.float() for k, v in sd.items() if k in own and own[k].shape == v.shape}
    branch = ("view_embedding.", "specific.", "importance.")
    fresh = [k for k in own if k not in take]
    if not all(k.startswith(branch) for k in fresh):  # (the configs matched: a bug)
        other = [k for k in fresh if not k.startswith(branch)]
        raise RuntimeError(f"model.init_from: {path}: weights outside the view-specific "
                           f"branch do not match: {other}")
    model.load_state_dict(take, strict=False)
    if fresh:
        log.info("model.init_from: %s: %d view-specific weight(s) start afresh (another "
                 "configuration of the branch): %s", path, len(fresh), ", ".join(fresh))
    return fresh


def _load_adding_importance(model, path: Path, cfg: UniqueSplatCfg, sd: dict) -> None:
    """The budget stage (docs/model.md): ``model`` is the checkpoint's model (any variant)
    with an importance head. Every weight of the checkpoint is loaded; the head keeps its
    initialisation (zero last layers: the model starts as the checkpoint, ranking by opacity)
    unless the checkpoint has one of the same shape."""
    if cfg.importance and cfg.importance_hidden != model.cfg.importance_hidden:
        sd = {k: v for k, v in sd.items() if not k.startswith("importance.")}
    missing, unexpected = model.load_state_dict(sd, strict=False)
    # the same config but the head (and _model_state checked the file against its config)
    assert not unexpected and all(k.startswith("importance.") for k in missing), (
        path, unexpected, missing)
    # (the cached W of H_a is dropped by itself: the loaded parameters' versions changed)


def export_weights(checkpoint: str | os.PathLike, out: str | os.PathLike, half: bool = True,
                   metadata: dict | None = None, trust: bool = False,
                   base: str | os.PathLike | None = None) -> Path:
    """A shippable copy of a training checkpoint: the model's weights (float16 when ``half``:
    half the bytes, and evaluation within 0.01 dB of float32, measured by
    ``train/ship_checkpoint.py``), its model config, training config, step, provenance and
    ``metadata``; no optimiser, scheduler or RNG state. Plain data only, so it loads with
    ``torch.load(weights_only=True)``; ``usplat eval/render/export-ply --checkpoint`` and
    ``model.init_from`` read it like a training checkpoint.

    ``base`` (a shipped checkpoint's name or a complete usplat checkpoint file): an add-on,
    holding only the weights that differ from ``base``'s (compared as stored: a model
    fine-tuned from a float16 file and frozen there gives back the same float16 values) and
    naming ``base`` by file name and sha256 (and the base's weights this model lacks, left out
    when it loads: a branch with another design). It loads like any checkpoint where that base
    lies beside it or among the shipped ones (``read_usplat_checkpoint``)."""
    state = read_usplat_checkpoint(checkpoint, trust=trust)
    if "model_config" not in state:
        raise ValueError(f"checkpoint {checkpoint} is not a usplat training checkpoint")
    weights = {k: (v.half() if half and v.is_floating_point() else v).contiguous()
               for k, v in state["model"].items()}
    shipped = {"format": "usplat-weights/1", "model": weights,
               "model_config": state["model_config"], "config": state.get("config", {}),
               "step": state.get("step", 0), "provenance": state.get("provenance", {}),
               "metadata": metadata or {}}
    if state.get("depth_range") is not None:  # the range of the scenes it was trained on
        shipped["depth_range"] = state["depth_range"]
    if base is not None:
        base_path = resolve_checkpoint(base)
        base_state = read_usplat_checkpoint(base_path, trust=trust)
        if "base" in base_state:
            raise ValueError(f"base: {base_path} is itself an add-on; name a complete one")
        inherited = base_state["model"]
        shipped["model"] = {
            k: v for k, v in weights.items()
            if k not in inherited or inherited[k].shape != v.shape
            or not torch.equal(inherited[k].double(), v.double())}
        shipped["base"] = {"file": base_path.name, "sha256": _file_sha256(base_path)}
        unused = sorted(set(inherited) - set(weights))
        if unused:  # the base's weights this model has no place for (another E_H, say)
            shipped["base"]["unused"] = unused
    return torch_save(shipped, out)


# ---- The shipped checkpoints ----

#: The shipped checkpoints ``usplat demo`` and ``usplat bench`` read (names in
#: ``CHECKPOINTS/manifest.json``, made by train/ship_checkpoint.py; usplat_dr.training.registry):
#: the trained primary network, and per variant the model fine-tuned from it for the same
#: steps (for (a): trained on, the control the others are paired with).
BASE = "baseline-64"
SHIPPED = {"baseline": "study/tiny_baseline_continued", "agnostic": "study/tiny_agnostic",
           "full": "study/tiny_full"}
#: The budget stage on SHIPPED's (a) and (c) (docs/model.md, "A Gaussian budget chosen at
#: inference"): add-ons holding the importance head, the rest their base's bit for bit (so
#: unbudgeted they render exactly as the SHIPPED ones); ``usplat demo`` charts their budgets.
BUDGETED = {"baseline": "study/tiny_baseline_budget", "full": "study/tiny_full_budget"}
#: The first (c) whose view-specific branch is live (its Delta W differs between target views:
#: E_H reading the primary network's features, trained alone at 32 scenes a step on a GPU; an
#: add-on on study/tiny_full). SHIPPED's (c) stays the paper's form; the demo shows its meter.
LIVE = "study/tiny_full_live"
#: The same branch trained with targets beyond the context views as well as between them
#: (``dataset.view_sampler.max_distance_beyond_context_views=4``; 300 steps on a CPU): its
#: Delta W differs between targets most where they leave the context pair (extrapolation); the
#: users' (c) at 64x64. The demo shows its meter on the standard and extrapolation splits.
BEYOND = "full-64"


def registered_verdict(root: Path = CHECKPOINTS) -> dict | None:
    """The multi-seed verdict shipped beside the checkpoints (``verdict.json``: the
    pre-registered rule's label per held-out set), or None where there is none."""
    path = root / "verdict.json"
    return json.loads(path.read_text()) if path.is_file() else None


def is_mvsplat_checkpoint(state: dict) -> bool:
    """Whether a loaded checkpoint is MVSplat's (a Lightning file whose ``state_dict`` keys
    start with ``encoder.``, or such a bare state dict) rather than one of ours."""
    sd = state.get("state_dict", state)
    return ("model_config" not in state and isinstance(sd, dict) and bool(sd)
            and all(isinstance(k, str) and k.startswith("encoder.") for k in sd))
