"""Resuming a training run: the checks that a checkpoint can continue this run (readable,
complete, dense weights, the same model and schedule), each failing as a ``ConfigError`` that
names the file and the fix, and the data position and random state put back."""

import logging
from pathlib import Path

import torch

from usplat_dr.config import ConfigError
from usplat_dr.io import UntrustedCheckpointError
from usplat_dr.training.checkpoints import foreign_tensor, read_usplat_checkpoint
from usplat_dr.training.config import RootCfg
from usplat_dr.training.distributed import set_rng_state

log = logging.getLogger(__name__)

#: What a checkpoint needs to be resumed (a shipped weights file has only the model).
RESUME_KEYS = ("model", "optimizer", "scheduler", "step", "rng", "data")

#: Settings fixed when a run starts (the learning-rate schedule's length and shape, the batch
#: the data position counts in): a resume with other values would run a schedule that does not
#: fit its optimiser state (torch: "Tried to step N times").
SCHEDULE_KEYS = ("train.steps", "optimizer.lr", "optimizer.warm_up_fraction",
                 "optimizer.hyper_lr_scale", "data_loader.batch_size")


def resumable_state(path: Path, device, trust: bool) -> dict:
    """The checkpoint ``path`` read, with what resuming needs; else a ``ConfigError``."""
    # tensors and plain data only: weights_only=True (model.trust_checkpoint, ``trust``, for
    # a file written before the RNG states were plain data)
    try:
        state = read_usplat_checkpoint(path, device, trust, cache=False)
    except UntrustedCheckpointError:
        raise  # its message names the opt-in
    except ValueError as e:  # truncated, not a torch file, not a dict
        raise ConfigError(f"--resume: {e}: move it away to start again from step "
                          f"0") from None
    bad = [k for k in RESUME_KEYS if k not in state]
    step = state.get("step")
    if not (isinstance(step, int) and not isinstance(step, bool) and step >= 0):
        bad.append("step")
    if bad:
        raise ConfigError(f"--resume: {path} has no usable {sorted(set(bad))} (a damaged "
                          f"checkpoint, or a shipped weights file: only usplat train's own "
                          f"last.ckpt resumes): move it away to start again from step 0")
    foreign = isinstance(state["model"], dict) and foreign_tensor(
        {k: v for k, v in state["model"].items() if isinstance(v, torch.Tensor)})
    if foreign:  # load_state_dict would cast it into the float32 weights silently
        raise ConfigError(f"--resume: {path}: {foreign}, where usplat train saves dense "
                          f"float32 (a damaged or foreign file): move it away to start "
                          f"again from step 0")
    return state


def check_same_schedule(path: Path, state: dict, config: RootCfg) -> None:
    """A ``ConfigError`` at the start of a resume whose schedule settings (``SCHEDULE_KEYS``)
    differ from the run's ``config`` (each named, with the value to pass), before any step is
    taken."""
    saved = state.get("config")
    if not isinstance(saved, dict):  # (checkpoints without their config: not checked)
        return
    differ = []
    for key in SCHEDULE_KEYS:
        section, name = key.split(".")
        was = saved.get(section, {}).get(name) if isinstance(saved.get(section), dict) \
            else None
        now = getattr(getattr(config, section), name)
        if was is not None and was != now:
            differ.append((key, was, now))
    if differ:
        raise ConfigError(
            f"--resume: {path} was started with "
            + ", ".join(f"{k}={w!r} (this run: {n!r})" for k, w, n in differ)
            + ": pass " + " ".join(f"{k}={w}" for k, w, _ in differ)
            + " to resume it (a run's schedule is fixed at its start), or choose another "
              "output_dir")


def differing_fields(saved: dict, current: dict, prefix: str = "") -> list[tuple]:
    """``(dotted name, saved value, current value)`` of the fields that both model configs
    have and set differently (lists and tuples alike). ``resnet_weights`` is not compared: a
    file of the machine that trained, whose weights the checkpoint holds.

    Examples:
        >>> differing_fields({"a": 1, "p": {"b": (1, 2)}}, {"a": 1, "p": {"b": [1, 3]}})
        [('p.b', (1, 2), [1, 3])]
    """
    out = []
    for key in sorted(set(saved) & set(current), key=str):
        was, now = saved[key], current[key]
        if key == "resnet_weights":
            continue
        if isinstance(was, dict) and isinstance(now, dict):
            out += differing_fields(was, now, f"{prefix}{key}.")
        elif (list(was) if isinstance(was, tuple) else was) != (
                list(now) if isinstance(now, tuple) else now):
            out.append((f"{prefix}{key}", was, now))
    return out


def check_same_model(path: Path, state: dict, model_config: dict, config: RootCfg) -> None:
    """A ``ConfigError`` when the checkpoint's model is not the one this run builds (its
    ``model_config``), naming ``model.variant`` / ``model.preset`` when those changed, else
    the fields."""
    saved = state.get("model_config")
    differ = differing_fields(saved, model_config) if isinstance(saved, dict) else []
    if not differ:
        return
    section = state.get("config")
    section = section.get("model") if isinstance(section, dict) else None
    section = section if isinstance(section, dict) else {}
    for key in ("variant", "preset"):
        was, now = section.get(key), getattr(config.model, key)
        if was is not None and was != now:
            raise ConfigError(f"--resume: {path} was trained with model.{key}={was}, this "
                              f"run asks for model.{key}={now}: pass model.{key}={was} to "
                              f"resume it, or choose another output_dir for a new run")
    name, was, now = differ[0]
    raise ConfigError(f"--resume: {path} was trained with another model ({len(differ)} "
                      f"field(s) of model_config differ; {name}: {was!r} there, {now!r} "
                      f"now): set model.overrides as they were (the checkpoint's 'config' "
                      f"holds them), or choose another output_dir for a new run")


def restore_position(path: Path, state: dict, batches, rank: int, world: int) -> None:
    """This rank's data position (into ``batches``) and random state from the checkpoint."""
    ranks = state.get("ranks") or [{"data": state["data"], "rng": state["rng"]}]
    if len(ranks) != world:
        log.warning("%s was written by %d rank(s), this run has %d: every rank resumes "
                    "rank 0's data position and random state, so the data order is not "
                    "an uninterrupted run's", path, len(ranks), world)
    mine = ranks[rank] if len(ranks) == world else ranks[0]
    try:
        batches.restore(mine["data"])
    except ConfigError as e:
        raise ConfigError(f"--resume: {path}: {e}") from None
    except (KeyError, TypeError) as e:
        raise ConfigError(f"--resume: {path} holds a damaged data position ({e!r}): move "
                          f"it away to start again from step 0") from None
    try:
        set_rng_state(mine["rng"])
    except (RuntimeError, ValueError, KeyError, TypeError) as e:
        detail = " ".join(str(e).split())[:200]
        raise ConfigError(f"--resume: {path} holds a damaged random state ({detail}): move "
                          f"it away to start again from step 0") from None


def load_training_state(path: Path, state: dict, model, optimizer, scheduler) -> None:
    """The checkpoint's model, optimiser and scheduler states loaded; a ``ConfigError`` naming
    ``path`` when they do not fit this run."""
    try:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
    except (RuntimeError, ValueError, KeyError, TypeError, IndexError) as e:
        detail = " ".join(str(e).split())[:300]  # one line (torch's lists span several)
        raise ConfigError(f"--resume: {path} does not fit this run ({type(e).__name__}: "
                          f"{detail}): resume with the settings it was trained with (its "
                          f"'config'), or move it away to start again from step "
                          f"0") from None
