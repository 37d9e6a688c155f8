"""Training: the field's recipe (Adam, one-cycle cosine schedule, gradient clipping at 0.5,
2 context + 4 target views, MSE + 0.05 LPIPS after a given step) on one process or under
``torchrun`` (DistributedDataParallel: gloo on CPU, nccl on GPU), CPU or CUDA.

Nothing is lost: checkpoints are written atomically every ``train.checkpoint_every`` steps and
on SIGINT/SIGTERM; ``resume`` continues exactly (model, optimiser, scheduler, step, RNG states,
data position: each rank's own, under torchrun). A step with a non-finite loss or gradient, or
whose forward pass meets non-finite values (the rasteriser's "must be finite"), is skipped with
a warning and counted; ``train.max_nonfinite`` of them in a row stop the run with a message and a
checkpoint of the last good state. Parameters that became non-finite are never saved: the run
stops at once, naming the last checkpoint (``TrainingStopped``).

A run holds its ``output_dir`` (``run_folder_lock``): a second run there stops at start-up,
naming the first's pid; on taking it, the temporary files of writes a killed run left are
removed. ``metrics.csv`` is rewritten atomically on start (a kill never loses its rows), and a
full disk is a ``DiskFull`` naming the file (``usplat_dr.training.run_log``, which also holds
TensorBoard and the progress bar). The loss terms are in ``usplat_dr.training.losses``.

``fit()`` is the loop: the per-step work (``next_step``), then the after-step hook
(``after_step``: the non-finite stop, the log, the checkpoint and validation cadences, the
signal stop and its vote across ranks), with the run folder, the signal handlers, the cores
kept awake and the run log held by one ``contextlib.ExitStack``.

Under torchrun every rank reads its own shard of the data (``usplat_dr.data.dataset``), takes
``data_loader.batch_size`` examples a step (the global batch is ranks x batch_size) and steps
with the gradient averaged over the ranks; the learning rate is used as configured, not scaled
with the ranks. All ranks stop after the same step on a signal; a rank that fails ends the
run with one message naming it (``usplat_dr.training.distributed.rank_failure``).
"""

import contextlib
import dataclasses
import fcntl
import logging
import math
import os
import random
import re
import signal
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, default_collate

from usplat_dr.config import ConfigError
from usplat_dr.data.dataset import ChunkDataset, dataset_from_section
from usplat_dr.data.types import model_inputs
from usplat_dr.data.view_sampler import StepTracker
from usplat_dr.evaluation import view_specificity
from usplat_dr.evaluation.figures import save_comparison
from usplat_dr.evaluation.lpips import LPIPS
from usplat_dr.evaluation.provenance import provenance, training_keys
from usplat_dr.io import UntrustedCheckpointError, torch_save
from usplat_dr.io.atomic import ATOMIC_TEMPORARY
from usplat_dr.training import cores as _cores
from usplat_dr.training.checkpoints import foreign_tensor, read_usplat_checkpoint
from usplat_dr.training.config import RootCfg, model_from_config
from usplat_dr.training.distributed import (
    gather,
    parameter_digest,
    rank_failure,
    rng_state,
    set_rng_state,
    setup_distributed,
)
from usplat_dr.training.losses import training_loss
from usplat_dr.training.run_log import RunLog, disk_full_names

log = logging.getLogger(__name__)

class TrainingStopped(RuntimeError):
    """Training stopped on purpose (non-finite steps); the message says why and where the last
    good checkpoint is."""


#: Messages of ``ValueError``s that mean non-finite values met in a step (the rasteriser's
#: "means must be finite, got NaN or Inf values"): the step is skipped like a NaN loss.
NON_FINITE = re.compile(r"\bfinite\b|\bNaN\b")


# ---- the run folder ----------------------------------------------------------------------------

#: The lock file of a run folder, held with ``fcntl.flock`` while a run trains there. The
#: kernel releases a flock when its process ends, however it ends: a SIGKILLed run leaves no
#: stale lock. The file holds the pid of its holder (for the message of a refused run).
LOCK_NAME = ".usplat-train.lock"
_held: dict[Path, list] = {}  # folder -> [lock's file descriptor, depth]: re-entrant


def _take_lock(folder: Path) -> int:
    """Create ``folder`` and take its lock (a file descriptor); a ``ConfigError`` naming the
    folder when it is a file, or another process holds the lock (naming its pid)."""
    if folder.exists() and not folder.is_dir():
        raise ConfigError(f"output_dir={folder} is an existing file, not a folder: choose "
                          f"another output_dir=... (or move the file away)")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise ConfigError(f"output_dir={folder}: a part of this path is a file, not a folder: "
                          f"choose another output_dir=...") from None
    fd = os.open(folder / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        pid = os.read(fd, 32).decode(errors="replace").strip()
        os.close(fd)
        who = f"pid {pid}" if pid.isdigit() else "pid unknown"
        raise ConfigError(f"output_dir={folder} is in use by another usplat train ({who}): "
                          f"wait for it to end or stop it, or choose another "
                          f"output_dir=...") from None
    try:  # the pid only informs a refused run's message: a failed write changes nothing
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
    except OSError:
        pass
    return fd


def remove_temporary_files(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporary files of killed atomic writes (``ATOMIC_TEMPORARY``) under
    ``folder``, recursively (symbolic links to folders are not followed); returns them. Call
    it only while holding the folder's lock: a running run's write in flight looks the same."""
    removed = []
    for parent, _, names in os.walk(folder):
        for name in names:
            if ATOMIC_TEMPORARY.fullmatch(name):
                path = Path(parent) / name
                path.unlink(missing_ok=True)
                removed.append(path)
    if removed:
        log.info("removed %d temporary file(s) of writes a killed run left in %s: %s",
                 len(removed), folder, ", ".join(str(p) for p in removed[:3]))
    return removed


@contextlib.contextmanager
def run_folder_lock(folder: str | os.PathLike) -> Iterator[Path]:
    """Hold the run folder ``folder`` (created if needed) for the block: another process
    asking for it meanwhile gets a ``ConfigError`` naming the folder and this process's pid.
    Re-entrant within a process. Taking it removes the temporary files killed writes left
    (``remove_temporary_files``). Also a ``ConfigError`` when ``folder`` is a file."""
    folder, key = Path(folder), Path(folder).resolve()
    first = key not in _held
    if first:
        _held[key] = [_take_lock(folder), 0]
    entry = _held[key]
    entry[1] += 1
    try:
        if first:
            remove_temporary_files(folder)
        yield folder
    finally:
        entry[1] -= 1
        if entry[1] == 0:
            del _held[key]
            os.close(entry[0])


def adam(params, lr: float) -> torch.optim.Adam:
    """Adam, fused where this torch has the fused kernel for the parameters' device (one
    kernel for all parameters: 31 -> 14 ms a step for the tiny preset's 1.7M parameters on
    one core; the same update up to float rounding). ``params``: tensors or param groups."""
    params = list(params)
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError):  # no fused kernel for this device or torch version
        return torch.optim.Adam(params, lr=lr)


# `float | int`, not `float`: beartype (pytest's run-time type checks) rejects an int for a float.
def parameter_groups(model: torch.nn.Module, lr: float | int,  # noqa: PYI041
                     hyper_lr_scale: float | int = 1.0) -> list[dict]:  # noqa: PYI041
    """Adam's parameter groups: the primary network at ``lr``; the hypernetwork branches
    (e_a and H_a, H_s, the view-specific features) and the importance head at
    ``lr * hyper_lr_scale`` (``optimizer.hyper_lr_scale``: the per-branch learning rate of
    docs/learning.md; 1 is the paper's single rate). One group when the scale is 1 or the
    model has no hypernetwork. Frozen parameters (``requires_grad`` off) are left out."""
    scale = float(hyper_lr_scale)
    if not (math.isfinite(scale) and scale > 0):
        raise ConfigError(f"optimizer.hyper_lr_scale must be a positive number, got "
                          f"{hyper_lr_scale!r}")
    primary, hyper = [], []
    for name, p in model.named_parameters():
        if p.requires_grad:  # (train.trainable=budget freezes the rest)
            (primary if name.split(".", 1)[0] == "primary" else hyper).append(p)
    if scale == 1.0 or not hyper:
        # model.parameters()'s order: Adam's state is keyed by position, so checkpoints of
        # runs before per-branch rates existed resume onto the same parameters
        return [{"params": [p for p in model.parameters() if p.requires_grad], "lr": lr}]
    groups = [{"params": primary, "lr": lr}, {"params": hyper, "lr": lr * scale}]
    return [g for g in groups if g["params"]]  # (frozen parameters are in neither)


class Batches:
    """An endless stream of batches over epochs, with a position (epoch, batches taken in the
    epoch) that a resumed run replays to: the same batches in the same order."""

    def __init__(self, dataset, batch_size: int, num_workers: int):
        self.dataset = dataset
        self.loader = DataLoader(dataset, batch_size=batch_size, num_workers=num_workers,
                                 persistent_workers=False)
        self.epoch, self.taken = 0, 0
        self._it = None

    def state(self) -> dict:
        """The position in the stream, for a checkpoint."""
        return {"epoch": self.epoch, "taken": self.taken}

    def restore(self, state: dict) -> None:
        """Go back to ``state()``'s position (the same batches follow). A ``ConfigError``
        when the epoch now has fewer batches than the position (the data changed)."""
        self.epoch, self.taken = state["epoch"], 0
        self.dataset.set_epoch(self.epoch)
        self._it = iter(self.loader)
        for _ in range(state["taken"]):  # replay (decodes the skipped batches once)
            try:
                next(self._it)
            except StopIteration:
                raise ConfigError(
                    f"its data position is batch {state['taken']} of epoch {self.epoch}, but "
                    f"the training set now gives {self.taken} batch(es) an epoch (the data "
                    f"under dataset.roots changed): put the data back, or start a new run in "
                    f"another output_dir") from None
            self.taken += 1

    def next(self) -> dict:
        """The next batch, starting a new epoch when one ends."""
        for _ in range(2):
            if self._it is None:
                self.dataset.set_epoch(self.epoch)
                self._it = iter(self.loader)
            try:
                batch = next(self._it)
                self.taken += 1
                return batch
            except StopIteration:
                self._it, self.epoch, self.taken = None, self.epoch + 1, 0
        raise ConfigError("the training set yields no examples (see the dataset summary "
                          "above: too few frames for the view sampler, or every scene skipped)")


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


def freeze_for_budget(model: torch.nn.Module, c: RootCfg) -> None:
    """Check the budget settings (``train.budget_fractions``, ``train.trainable``) against the
    model (a ``ConfigError`` naming the key and the fix) and freeze what ``train.trainable``
    leaves out: for ``budget`` every parameter but the importance head's and the adaptation's,
    for ``view_specific`` every parameter but the view-specific branch's (E_H, the lateral
    convs, Proj, phi and H_s)."""
    tc = c.train
    head = getattr(model, "importance", None)
    if (tc.budget_fractions or tc.trainable == "budget") and head is None:
        raise ConfigError("train.budget_fractions and train.trainable=budget need a model "
                          "with an importance head: set model.overrides.importance=true (the "
                          "config synthetic_tiny_budget.yaml does)")
    if tc.trainable == "view_specific":
        if getattr(model, "specific", None) is None:
            raise ConfigError("train.trainable=view_specific trains the view-specific branch, "
                              "which this model lacks: set model.variant=full")
        for name, p in model.named_parameters():
            p.requires_grad_(name.split(".", 1)[0] in ("view_embedding", "specific"))
        return
    if tc.trainable != "budget":
        return
    if not tc.budget_fractions or (tc.budget_sampling == "choice"
                                   and all(f == 1 for f in tc.budget_fractions)):
        raise ConfigError("train.trainable=budget trains only the importance head, which a "
                          "step learns from only when its budget keeps fewer than all the "
                          "Gaussians: set train.budget_fractions below 1")
    if tc.budget_sampling == "choice" and 1.0 in tc.budget_fractions:
        raise ConfigError(f"train.budget_fractions={list(tc.budget_fractions)} holds 1 with "
                          f"train.trainable=budget: such a step keeps every Gaussian and "
                          f"leaves nothing to train (the loss has no gradient); drop it")
    for name, p in model.named_parameters():
        p.requires_grad_(name.split(".", 1)[0] == "importance")


def widened_depth_range(depth_range: list[float] | None, near: torch.Tensor,
                        far: torch.Tensor) -> list[float]:
    """``depth_range`` ([min near, max near, min far, max far], or ``None``) widened to hold
    a batch's ``near`` and ``far`` (any shape).

    Examples:
        >>> widened_depth_range(None, torch.tensor([[1.0, 2.0]]), torch.tensor([[50.0, 9.0]]))
        [1.0, 2.0, 9.0, 50.0]
        >>> widened_depth_range([1.0, 2.0, 9.0, 50.0], torch.tensor([0.5]), torch.tensor([20.0]))
        [0.5, 2.0, 9.0, 50.0]
    """
    now = torch.stack([near.min(), near.max(), far.min(), far.max()]).double().tolist()
    if depth_range is None:
        return now
    return [min(depth_range[0], now[0]), max(depth_range[1], now[1]),
            min(depth_range[2], now[2]), max(depth_range[3], now[3])]


def step_budget(c: RootCfg, step: int) -> dict:
    """The budget of step ``step``: ``forward``'s ``budget``, ``budget_tau`` and ``rank_by``
    (``{}`` without ``train.budget_fractions``). Drawn from a generator seeded with the run's
    seed and the step: the same on every rank and after a resume, and no RNG state touched."""
    tc = c.train
    if not tc.budget_fractions:
        return {}
    rng = random.Random(c.seed * 1_000_003 + step)
    if tc.budget_sampling == "choice":
        fraction = rng.choice(tc.budget_fractions)
    else:
        lo, hi = math.log(min(tc.budget_fractions)), math.log(max(tc.budget_fractions))
        fraction = math.exp(rng.uniform(lo, hi))
    t0, t1 = tc.budget_tau
    tau = t0 * (t1 / t0) ** min(step / max(tc.steps - 1, 1), 1.0)
    return {"budget": float(fraction), "budget_tau": tau, "rank_by": "learned"}


# ---- the trainer -------------------------------------------------------------------------------

class Trainer:
    """The training loop of one process (one rank under ``torchrun``): ``fit()`` trains to
    ``train.steps``, ``resume()`` continues from a checkpoint, ``train_step(batch)`` is one
    optimiser step, ``validate()`` renders the validation scene.

    ``cfg``: a loaded config (``usplat_dr.config.load_config``; checked into ``RootCfg``, so a
    wrong key or type stops here naming it) or a ``RootCfg``. ``self.config`` is the typed
    configuration; ``self.cfg`` the same as plain data with every default filled in (saved in
    checkpoints: the whole recipe of the run)."""

    def __init__(self, cfg: dict | RootCfg):
        self.config = cfg if isinstance(cfg, RootCfg) else RootCfg.load(cfg)
        self.cfg = dataclasses.asdict(self.config)
        c = self.config
        self.out = Path(c.output_dir)
        self.rank, self.world, self.device = setup_distributed(c.device, c.threads)
        seed = c.seed
        # The same seed on every rank: identical initial weights (DDP would broadcast rank 0's
        # anyway); the data is sharded by the dataset and its samplers have their own seeds.
        torch.manual_seed(seed)
        np.random.seed(seed)
        random.seed(seed)

        self.lpips = None
        if c.loss.lpips > 0 and c.loss.lpips_after_step < c.train.steps:
            # Stops at start-up (not at step 150k) when the files are missing.
            self.lpips = LPIPS.from_files(c.loss.lpips_vgg, c.loss.lpips_lin).to(self.device)

        self.model = model_from_config(c.model).to(self.device)
        freeze_for_budget(self.model, c)
        self.ddp = self.model
        if self.world > 1:
            # a step whose budget keeps everything leaves the importance head unused
            self.ddp = torch.nn.parallel.DistributedDataParallel(
                self.model, find_unused_parameters=bool(c.train.budget_fractions))
        self.step_tracker = StepTracker()
        self.batches = Batches(dataset_from_section(c.dataset, "train", self.step_tracker),
                               c.data_loader.batch_size, c.data_loader.num_workers)
        groups = parameter_groups(self.model, c.optimizer.lr, c.optimizer.hyper_lr_scale)
        self.optimizer = adam(groups, c.optimizer.lr)
        self.scheduler = torch.optim.lr_scheduler.OneCycleLR(
            self.optimizer, [g["lr"] for g in groups], total_steps=c.train.steps + 10,
            pct_start=c.optimizer.warm_up_fraction, cycle_momentum=False,
            anneal_strategy="cos")
        # What this run ran on (data content hash, library versions, CPU, threads): saved
        # in every checkpoint, so runs that differ can be told apart.
        # The training scenes' keys too: ``usplat eval`` warns when it scores one of them.
        self.provenance = ({**provenance(c.dataset.roots),
                            "train_keys": training_keys(c.dataset.roots)}
                           if self.rank == 0 else {})
        self.step = 0
        self.skipped = 0
        # [min near, max near, min far, max far] of the batches trained on: saved, so that
        # ``render``/``view`` can warn when a scene's range lies far outside it
        self.depth_range: list[float] | None = None
        self.saved_step = None  # the step of this run's checkpoint
        self.consecutive_bad = 0
        self._stop_signal = None
        self._val_batch = None

    # -- checkpoints --
    @property
    def checkpoint_path(self) -> Path:
        """``output_dir/checkpoints/last.ckpt``."""
        return self.out / "checkpoints" / "last.ckpt"

    def save(self) -> Path | None:
        """Write the checkpoint atomically (rank 0; other ranks return ``None``). Under
        torchrun every rank calls it at the same step: it gathers each rank's data position
        and RNG states (``ranks``), so that each resumes exactly where it was. Parameters
        that are not finite are never saved: a ``TrainingStopped`` names the last checkpoint;
        a full disk is a ``DiskFull`` naming the file."""
        if not self.parameters_finite():
            raise TrainingStopped(f"the parameters are non-finite (NaN or Inf) at step "
                                  f"{self.step}; stopped without saving them. "
                                  f"{self.last_good()}")
        ranks = gather({"data": self.batches.state(), "rng": rng_state()})
        if self.rank != 0:
            self.saved_step = self.step
            return None
        state = {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                 "scheduler": self.scheduler.state_dict(), "step": self.step,
                 "rng": ranks[0]["rng"], "data": ranks[0]["data"], "skipped": self.skipped,
                 "config": self.cfg, "model_config": self.model.cfg.to_dict(),
                 "provenance": self.provenance, "depth_range": self.depth_range}
        if self.world > 1:
            state["ranks"] = ranks
        with disk_full_names(self.checkpoint_path):
            path = torch_save(state, self.checkpoint_path)
        keep = self.config.train.keep_every
        if keep and self.step % keep == 0:  # a copy that later checkpoints leave alone
            kept = self.checkpoint_path.with_name(f"step_{self.step:07d}.ckpt")
            with disk_full_names(kept):
                torch_save(state, kept)
        self.saved_step = self.step
        return path

    @torch.no_grad()
    def parameters_finite(self) -> bool:
        """Whether every parameter is finite (from each one's largest |value|: a 2-norm
        would overflow to inf on large finite weights)."""
        largest = torch._foreach_norm(list(self.model.parameters()), float("inf"))
        return bool(torch.stack(largest).isfinite().all())

    def last_good(self) -> str:
        """Where the last good state of this run is, and what to do (for messages)."""
        if self.saved_step is None:
            return ("No checkpoint of this run holds a good state: lower optimizer.lr (or "
                    "check the data) and start again")
        return (f"The last good state is in {self.checkpoint_path} (step {self.saved_step}): "
                f"lower optimizer.lr (or check the data), then resume with --resume")

    def resume(self, path: str | os.PathLike | None = None) -> bool:
        """Continue from ``path`` (default: this run's last checkpoint). False when there is
        none to resume from. A checkpoint that is damaged, of another model, or whose data
        position the training set no longer has is a ``ConfigError`` naming it and the fix."""
        path = Path(path) if path else self.checkpoint_path
        if not path.is_file():
            return False
        state = self._resumable_state(path)
        self._check_same_model(path, state)
        self._check_same_schedule(path, state)
        try:
            self.model.load_state_dict(state["model"])
            self.optimizer.load_state_dict(state["optimizer"])
            self.scheduler.load_state_dict(state["scheduler"])
        except (RuntimeError, ValueError, KeyError, TypeError, IndexError) as e:
            detail = " ".join(str(e).split())[:300]  # one line (torch's lists span several)
            raise ConfigError(f"--resume: {path} does not fit this run ({type(e).__name__}: "
                              f"{detail}): resume with the settings it was trained with (its "
                              f"'config'), or move it away to start again from step "
                              f"0") from None
        self.step, self.skipped = state["step"], state.get("skipped", 0)
        self.depth_range = state.get("depth_range")
        self.saved_step = self.step
        self.step_tracker.set_step(self.step)
        self._restore_position(path, state)
        log.info("resumed from %s at step %d", path, self.step)
        return True

    #: What a checkpoint needs to be resumed (a shipped weights file has only the model).
    RESUME_KEYS = ("model", "optimizer", "scheduler", "step", "rng", "data")

    def _resumable_state(self, path: Path) -> dict:
        """The checkpoint ``path`` read, with what resuming needs; else a ``ConfigError``."""
        # tensors and plain data only: weights_only=True (model.trust_checkpoint for a file
        # written before the RNG states were plain data)
        try:
            state = read_usplat_checkpoint(path, self.device,
                                           self.config.model.trust_checkpoint)
        except UntrustedCheckpointError:
            raise  # its message names the opt-in
        except ValueError as e:  # truncated, not a torch file, not a dict
            raise ConfigError(f"--resume: {e}: move it away to start again from step "
                              f"0") from None
        bad = [k for k in self.RESUME_KEYS if k not in state]
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

    #: Settings fixed when a run starts (the learning-rate schedule's length and shape, the
    #: batch the data position counts in): a resume with other values would run a schedule
    #: that does not fit its optimiser state (torch: "Tried to step N times").
    SCHEDULE_KEYS = ("train.steps", "optimizer.lr", "optimizer.warm_up_fraction",
                     "optimizer.hyper_lr_scale", "data_loader.batch_size")

    def _check_same_schedule(self, path: Path, state: dict) -> None:
        """A ``ConfigError`` at the start of a resume whose schedule settings differ from the
        run's (each named, with the value to pass), before any step is taken."""
        saved = state.get("config")
        if not isinstance(saved, dict):  # (checkpoints without their config: not checked)
            return
        differ = []
        for key in self.SCHEDULE_KEYS:
            section, name = key.split(".")
            was = saved.get(section, {}).get(name) if isinstance(saved.get(section), dict) \
                else None
            now = getattr(getattr(self.config, section), name)
            if was is not None and was != now:
                differ.append((key, was, now))
        if differ:
            raise ConfigError(
                f"--resume: {path} was started with "
                + ", ".join(f"{k}={w!r} (this run: {n!r})" for k, w, n in differ)
                + ": pass " + " ".join(f"{k}={w}" for k, w, _ in differ)
                + " to resume it (a run's schedule is fixed at its start), or choose another "
                  "output_dir")

    def _check_same_model(self, path: Path, state: dict) -> None:
        """A ``ConfigError`` when the checkpoint's model is not the one this run builds,
        naming ``model.variant`` / ``model.preset`` when those changed, else the fields."""
        saved = state.get("model_config")
        differ = (differing_fields(saved, self.model.cfg.to_dict())
                  if isinstance(saved, dict) else [])
        if not differ:
            return
        config = state.get("config")
        section = config.get("model") if isinstance(config, dict) else None
        section = section if isinstance(section, dict) else {}
        for key in ("variant", "preset"):
            was, now = section.get(key), getattr(self.config.model, key)
            if was is not None and was != now:
                raise ConfigError(f"--resume: {path} was trained with model.{key}={was}, this "
                                  f"run asks for model.{key}={now}: pass model.{key}={was} to "
                                  f"resume it, or choose another output_dir for a new run")
        name, was, now = differ[0]
        raise ConfigError(f"--resume: {path} was trained with another model ({len(differ)} "
                          f"field(s) of model_config differ; {name}: {was!r} there, {now!r} "
                          f"now): set model.overrides as they were (the checkpoint's 'config' "
                          f"holds them), or choose another output_dir for a new run")

    def _restore_position(self, path: Path, state: dict) -> None:
        """This rank's data position and random state from the checkpoint."""
        ranks = state.get("ranks") or [{"data": state["data"], "rng": state["rng"]}]
        if len(ranks) != self.world:
            log.warning("%s was written by %d rank(s), this run has %d: every rank resumes "
                        "rank 0's data position and random state, so the data order is not "
                        "an uninterrupted run's", path, len(ranks), self.world)
        mine = ranks[self.rank] if len(ranks) == self.world else ranks[0]
        try:
            self.batches.restore(mine["data"])
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

    # -- one step --
    def loss(self, out, batch: dict) -> tuple[torch.Tensor, dict]:
        """MSE on the targets, + LPIPS after ``loss.lpips_after_step``, + the depth terms
        (``loss.depth`` on the context views, ``loss.target_depth`` on the rendered targets;
        until ``loss.depth_until_step``) where the data has depth
        (``usplat_dr.training.losses.training_loss``)."""
        return training_loss(out, batch, self.config.loss, self.step, self.device, self.lpips)

    #: Parameter groups whose gradient norms (before clipping) go into metrics.csv: the
    #: primary network, the view-agnostic branch (e_a, H_a), the view-specific hypernetwork
    #: H_s and the view-specific features (ResNet18, lateral convs, Proj, phi).
    GRAD_GROUPS: ClassVar[dict[str, str]] = {
        "primary": "grad_primary", "agnostic": "grad_agnostic",
        "specific": "grad_specific", "view_embedding": "grad_view_features",
        "importance": "grad_importance"}

    def group_grad_norms(self) -> dict:
        """Gradient norms per part of the network (``GRAD_GROUPS``), before clipping."""
        groups: dict[str, list[torch.Tensor]] = {}
        for name, p in self.model.named_parameters():
            key = self.GRAD_GROUPS.get(name.split(".", 1)[0])
            if key is not None and p.grad is not None:
                groups.setdefault(key, []).append(p.grad.detach())
        # One foreach kernel per group (a per-parameter float64 sum cost ~14 ms a step).
        norms = {k: torch.stack(torch._foreach_norm(g)).norm() for k, g in groups.items()}
        return dict(zip(norms, torch.stack(list(norms.values())).tolist())) if norms else {}

    @torch.no_grad()
    def clip_gradients(self) -> tuple[torch.Tensor, dict]:
        """Clip the gradients to a global norm of ``optimizer.gradient_clip``; returns the
        norm before clipping and ``group_grad_norms()``. The same numbers as those two calls
        (``group_grad_norms`` then ``torch.nn.utils.clip_grad_norm_``), from one pass over the
        per-parameter norms instead of two (~2 ms of a 64x64 tiny step at two threads)."""
        max_norm = self.config.optimizer.gradient_clip
        named = [(n, p.grad) for n, p in self.model.named_parameters() if p.grad is not None]
        grads = [g for _, g in named]
        if not grads or len({(g.device, g.dtype) for g in grads}) > 1:
            parts = self.group_grad_norms()  # torch's own grouping by device and dtype
            return torch.nn.utils.clip_grad_norm_(self.model.parameters(), max_norm), parts
        norms = torch._foreach_norm(grads)
        groups: dict[str, list[torch.Tensor]] = {}
        for (name, _), n in zip(named, norms):
            key = self.GRAD_GROUPS.get(name.split(".", 1)[0])
            if key is not None:
                groups.setdefault(key, []).append(n)
        group_norms = [torch.stack(v).norm() for v in groups.values()]
        parts = dict(zip(groups, torch.stack(group_norms).tolist())) if groups else {}
        # clip_grad_norm_'s arithmetic, step for step: the norm of the stacked norms, then
        # every gradient times min(1, max_norm / (norm + 1e-6))
        total = torch.linalg.vector_norm(torch.stack(norms), 2.0)
        torch._foreach_mul_(grads, torch.clamp(max_norm / (total + 1e-6), max=1.0))
        return total, parts

    def train_step(self, batch: dict) -> dict | None:
        """One optimiser step on ``batch``: its statistics, or ``None`` when the loss or
        gradient is not finite, or the forward pass met non-finite values (a ``ValueError``
        matching ``NON_FINITE``, e.g. the rasteriser's "means must be finite"): no update,
        BatchNorm statistics restored; the learning-rate schedule advances as for any step."""
        self.ddp.train()
        args = model_inputs(batch, self.device)
        target = batch["target"]["image"].to(self.device)
        self.depth_range = widened_depth_range(self.depth_range, args.near, args.far)
        self.optimizer.zero_grad(set_to_none=True)
        # BatchNorm statistics change in the forward pass: kept to be put back if the step
        # is skipped (a NaN input would otherwise poison them for good)
        buffers = {n: b.detach().clone() for n, b in self.model.named_buffers()}
        budget = step_budget(self.config, self.step)
        try:
            out = self.ddp(*args, global_step=self.step, **budget)
            loss, parts = self.loss(out, batch)
            loss.backward()
        except ValueError as e:
            if not NON_FINITE.search(str(e)):
                raise
            if self.world > 1:  # the other ranks wait in this step's collectives: stop all
                raise TrainingStopped(f"step {self.step}: {e}; stopped. "
                                      f"{self.last_good()}") from None
            return self._skip(buffers, f"non-finite values in the forward pass ({e})")
        norm, grad_norms = self.clip_gradients()
        parts.update(grad_norms)
        finite = torch.isfinite(loss) & torch.isfinite(norm)
        if self.world > 1:  # every rank takes the same decision
            flag = finite.float().to(self.device)
            dist.all_reduce(flag, op=dist.ReduceOp.MIN)
            finite = flag > 0
        if not bool(finite):
            return self._skip(buffers, f"non-finite loss or gradient (loss {loss.item()}, "
                                       f"grad norm {norm.item()})")
        self.consecutive_bad = 0
        self.optimizer.step()
        self.scheduler.step()
        with torch.no_grad():
            mse = (out.color.clamp(0, 1) - target).square().mean((-3, -2, -1))
            psnr = (-10 * torch.log10(mse.clamp(min=1e-10))).mean().item()
        if budget:
            parts["budget"] = budget["budget"]
        return {"loss": loss.item(), "psnr": psnr, "grad_norm": norm.item(),
                "lr": self.scheduler.get_last_lr()[0], **parts}

    def _skip(self, buffers: dict, why: str) -> None:
        """Skip this step (``why``, for the warning): no update, the BatchNorm statistics
        ``buffers`` put back, the schedule advanced."""
        self.skipped += 1
        self.consecutive_bad += 1
        log.warning("step %d: %s; step skipped (%d so far)", self.step, why, self.skipped)
        self.optimizer.zero_grad(set_to_none=True)
        with torch.no_grad():
            for n, b in self.model.named_buffers():
                if n in buffers:
                    b.copy_(buffers[n])
        # A skipped step still counts (its batch is consumed, ``step`` advances), and the
        # learning rate stays a function of ``step``: the schedule advances too, so a run
        # with skips ends its schedule at ``train.steps`` like one without. (torch warns
        # when the very first step is skipped, the optimizer not having stepped yet; the
        # schedule's first value is then consumed by the skipped step, as intended.)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r"Detected call of `lr_scheduler")
            self.scheduler.step()

    def _stop_if_diverged(self) -> None:
        """After a skipped step, a ``TrainingStopped`` when the parameters are no longer
        finite (every later step would fail too; they are not saved) or after
        ``train.max_nonfinite`` skipped steps in a row (the state is saved: the parameters
        of the last good step)."""
        if not self.parameters_finite():
            raise TrainingStopped(f"the parameters are non-finite (NaN or Inf) after step "
                                  f"{self.step}; stopped without saving them. "
                                  f"{self.last_good()}")
        if self.consecutive_bad >= self.config.train.max_nonfinite:
            path = self.save()
            raise TrainingStopped(
                f"{self.consecutive_bad} steps in a row had a non-finite loss or "
                f"gradient (last at step {self.step}); stopped. The last good state "
                f"is in {path or self.checkpoint_path}: lower optimizer.lr or check "
                f"the data, then resume")

    # -- the loop --
    def _on_signal(self, signum, frame):
        self._stop_signal = signum
        log.warning("signal %d: saving a checkpoint after this step", signum)

    def hold_folder(self) -> contextlib.AbstractContextManager:
        """Hold ``output_dir`` (``run_folder_lock``) on rank 0, which alone writes there;
        other ranks get a context that does nothing. ``fit()`` holds it; ``train()`` holds it
        across ``resume()`` and ``fit()``."""
        return run_folder_lock(self.out) if self.rank == 0 else contextlib.nullcontext()

    #: The columns of metrics.csv.
    METRICS = ("step", "loss", "mse", "lpips", "depth", "target_depth", "budget", "full_mse",
               "psnr", "grad_norm",
               *GRAD_GROUPS.values(), "view_spread", "view_psnr_abs", "view_psnr_zero", "lr",
               "skipped", "steps_per_s", "time_s", "cpu_s")

    def fit(self) -> dict:
        """Train to ``train.steps`` (or a signal), logging, checkpointing and validating
        on the way (``after_step``); returns the last step's statistics. Meanwhile it holds
        the run folder, catches SIGINT/SIGTERM, keeps the cores awake where wanted and keeps
        the run log open; it lets them go in the reverse order however the loop ends."""
        with contextlib.ExitStack() as held:
            held.enter_context(self.hold_folder())
            held.enter_context(self._signals_caught())
            held.enter_context(self._cores_awake())
            run_log = held.enter_context(self._run_log())
            last = {}  # the last good step's statistics
            while self.step < self.config.train.steps:
                stats = self.next_step()
                last = stats if stats is not None else last
                if self.after_step(stats, last, run_log):
                    break
        digest = parameter_digest(self.model)
        if len(set(gather(digest))) > 1:  # DDP keeps them equal; if not, say so
            log.error("rank %d: the ranks hold different parameters after step %d (digests "
                      "%s); the checkpoint holds rank 0's", self.rank, self.step,
                      gather(digest))
        return {"step": self.step, "skipped": self.skipped, "rank": self.rank,
                "params_sha256": digest, **last}

    @contextlib.contextmanager
    def _signals_caught(self) -> Iterator[None]:
        """SIGINT and SIGTERM call ``_on_signal`` in the block (the run saves and stops after
        the step: ``after_step``); the handlers from before come back after it."""
        old = {s: signal.signal(s, self._on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield
        finally:
            for s, h in old.items():
                signal.signal(s, h)

    def _cores_awake(self) -> contextlib.AbstractContextManager:
        """Idle-priority spinners (``CoreKeeper``) for the block where ``keep_cores_awake``
        wants them (``usplat_dr.training.cores.decide``: the setting, or a probe of how fast
        idle cores wake), else a context that does nothing; logs which and why."""
        on, why = _cores.decide(self.config.keep_cores_awake, torch.get_num_threads(),
                                self.device.type)
        log.info("%s", _cores.log_line(on, why))
        if on:
            return _cores.CoreKeeper()
        return contextlib.nullcontext()

    def _run_log(self) -> contextlib.AbstractContextManager:
        """Rank 0's ``RunLog`` from this step on (metrics.csv, TensorBoard, the progress bar);
        on the other ranks, which log nothing, a context that gives ``None``."""
        if self.rank != 0:
            return contextlib.nullcontext()
        tc = self.config.train
        return RunLog(self.out, self.METRICS, self.step, tc.steps, tc.log_every, tc.progress)

    def next_step(self) -> dict | None:
        """The loop's work for one step: the next batch (the first also picks the validation
        batch) and ``train_step`` on it; its statistics, ``None`` when it was skipped."""
        self.step_tracker.set_step(self.step)
        batch = self.batches.next()
        if self._val_batch is None:
            self._val_batch = self.validation_batch(batch)
        return self.train_step(batch)

    def after_step(self, stats: dict | None, last: dict, run_log: RunLog | None) -> bool:
        """The after-step hook: what follows ``next_step``, in order; True to stop.

        A skipped step (``stats`` is ``None``) stops the run when the parameters went
        non-finite or ``train.max_nonfinite`` steps in a row were skipped
        (``_stop_if_diverged``: before the step counts, so its checkpoint holds the last good
        state at this step). Then the step counts and ``run_log`` logs it (``last``: the last
        good step's statistics); a checkpoint every ``train.checkpoint_every`` steps and at the
        last one; rank 0's validation grid every ``train.validate_every`` steps and at the last
        one; and after SIGINT/SIGTERM on any rank, a checkpoint and the stop, all ranks after
        the same step (``_stopped_by_signal``)."""
        if stats is None:
            self._stop_if_diverged()
        self.step += 1
        tc = self.config.train
        validating = self.rank == 0 and (self.step % tc.validate_every == 0
                                         or self.step == tc.steps)
        if run_log is not None:
            # the meter on the validation scene, where metrics.csv writes this step's row
            logged = self.step % tc.log_every == 0 or self.step == tc.steps
            meter = self.view_meter() if validating and logged and last else {}
            run_log.log(self.step, {**last, **meter}, self.skipped)
        if self.step % tc.checkpoint_every == 0 or self.step == tc.steps:
            self.save()
        if validating:
            self.validate()
        return self._stopped_by_signal()

    def _stopped_by_signal(self) -> bool:
        """After a SIGINT/SIGTERM: save and say so (all ranks stop after the same step)."""
        stop = self._stop_signal is not None
        if self.world > 1:  # all ranks stop after the same step (else: a hang)
            flag = torch.tensor(float(stop), device=self.device)
            dist.all_reduce(flag, op=dist.ReduceOp.MAX)
            stop = bool(flag > 0)
        if stop:
            self.save()
            who = f"rank {self.rank} " if self.world > 1 else ""
            log.warning("%sstopped by signal %s at step %d; resume with --resume", who,
                        self._stop_signal, self.step)
        return stop

    def validation_batch(self, fallback: dict) -> dict:
        """The first example of the validation stage (the dataset's test folder) when there
        is one, else ``fallback`` (a training batch)."""
        try:
            ds = dataset_from_section(self.config.dataset, "val")
            example = next(iter(ds), None) if isinstance(ds, ChunkDataset) else None
        except (ValueError, FileNotFoundError, StopIteration):
            example = None
        if example is None:
            first = {side: {k: v[:1] for k, v in fallback[side].items()}
                     for side in ("context", "target")}
            return {**first, "scene": fallback["scene"][:1]}  # save_comparison names it
        return default_collate([example])

    def view_meter(self) -> dict:
        """The view-specificity meter (``usplat_dr.evaluation.view_specificity``) on the
        validation scene, for metrics.csv at validation steps that write a row:
        ``view_spread`` (how much Delta W differs between its targets, relative to ||W||, the
        largest over the layers) and, in dB, ``view_psnr_abs`` (mean |PSNR(per-target Delta
        W) - PSNR(the scene's mean)|) and ``view_psnr_zero`` (PSNR(per-target) - PSNR(Delta W
        = 0)). ``{}`` for a model without the view-specific branch or a validation scene with
        one target. Rank 0 only (no collectives): the other ranks never call it."""
        batch = self._val_batch
        if (batch is None or getattr(self.model, "specific", None) is None
                or batch["target"]["image"].shape[1] < 2):
            return {}
        (r,) = view_specificity.read_batch(self.model, batch, self.device)
        return {"view_spread": max(r.spread.values()), "view_psnr_abs": r.d_mean_abs,
                "view_psnr_zero": r.d_zero}

    @torch.no_grad()
    def validate(self) -> Path | None:
        """A PNG grid of the validation scene: context | target | prediction | depth, a row
        per target view."""
        if self._val_batch is None:
            return None
        self.model.eval()
        out = self.model(*model_inputs(self._val_batch, self.device))
        # validation/step_0000002_<scene>.png (save_comparison names the file after the scene)
        return save_comparison(self.out / "validation", self._val_batch, out,
                               prefix=f"step_{self.step:07d}_")


def train(cfg: dict | RootCfg, resume: bool = False) -> dict:
    """Train with ``cfg`` (see ``Trainer``), from the last checkpoint when ``resume`` and one
    exists; returns the last step's statistics (``step``, ``skipped``, ``loss``, ``psnr``,
    ``rank``, ``params_sha256``...). The run folder is held (rank 0) once the configuration,
    model and data are checked, before anything is read from it or written there: a second run
    there stops then, and a mistaken configuration leaves no folder behind.

    Under torchrun, an exception on any rank becomes ``RankFailed`` on every rank, with the
    message of the rank that failed first (``usplat_dr.training.distributed.rank_failure``);
    its traceback is logged there, unless it is a ``ConfigError`` (data and configuration
    errors, whose message says it all) or ``TrainingStopped``."""
    trainer = None
    try:
        trainer = Trainer(cfg)
        with trainer.hold_folder():
            if resume and not trainer.resume():
                log.info("no checkpoint in %s: starting from step 0",
                         trainer.checkpoint_path.parent)
            result = trainer.fit()
    except Exception as e:
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1:
            raise
        rank = int(os.environ.get("RANK", "0"))
        failure = rank_failure(e, rank, world, trainer.step if trainer is not None else None)
        if failure.own and not isinstance(e, (ConfigError, TrainingStopped)):
            log.error("rank %d: traceback of the failure", rank, exc_info=e)
        raise failure from e
    if dist.is_initialized():
        dist.destroy_process_group()
    return result
