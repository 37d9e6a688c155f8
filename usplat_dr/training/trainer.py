"""The training loop (``Trainer``): the field's recipe (Adam, one-cycle cosine schedule,
gradient clipping at 0.5, 2 context + 4 target views, MSE + 0.05 LPIPS after a given step) on
one process or as one rank under ``torchrun`` (DistributedDataParallel), CPU or CUDA.

Nothing is lost: checkpoints are written atomically every ``train.checkpoint_every`` steps and
on SIGINT/SIGTERM; ``resume`` continues exactly (``usplat_dr.training.resume``). A step with a
non-finite loss or gradient, or whose forward pass meets non-finite values, is skipped with a
warning and counted; ``train.max_nonfinite`` of them in a row stop the run with the last good
state saved; parameters that became non-finite are never saved (``TrainingStopped``).

``fit()`` is the loop: ``next_step`` then ``after_step`` (the non-finite stop, the log, the
checkpoint and validation cadences, the signal stop voted across ranks), holding the run folder,
the signal handlers and the cores (``usplat_dr.training.run_folder``) and the run log
(``usplat_dr.training.run_log``). ``train()`` (``usplat_dr.training.launch``) is the entry.
Under torchrun every rank reads its own shard of the data and steps with the gradient averaged
over the ranks; all ranks stop after the same step on a signal.
"""

import contextlib
import dataclasses
import logging
import os
import random
import re
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from usplat_dr.data.dataset import dataset_from_section
from usplat_dr.data.types import model_inputs
from usplat_dr.data.view_sampler import StepTracker
from usplat_dr.evaluation.lpips import LPIPS
from usplat_dr.evaluation.provenance import provenance, training_keys
from usplat_dr.io import torch_save
from usplat_dr.training.batches import Batches
from usplat_dr.training.checkpoints import widened_depth_range
from usplat_dr.training.config import RootCfg, model_from_config
from usplat_dr.training.distributed import (
    gather,
    parameter_digest,
    rng_state,
    set_tf32,
    setup_distributed,
)
from usplat_dr.training.losses import training_loss
from usplat_dr.training.optim import GRAD_GROUPS, clip_gradients, optimiser_and_schedule
from usplat_dr.training.resume import (
    check_same_model,
    check_same_schedule,
    load_training_state,
    restore_position,
    resumable_state,
)
from usplat_dr.training.run_folder import cores_awake, run_folder_lock, signals_caught
from usplat_dr.training.run_log import RunLog, disk_full_names
from usplat_dr.training.stages import freeze_for_budget, step_budget
from usplat_dr.training.validation import validation_batch, validation_grid, view_meter

log = logging.getLogger(__name__)

class TrainingStopped(RuntimeError):
    """Training stopped on purpose (non-finite steps); the message says why and where the last
    good checkpoint is."""


#: Messages of ``ValueError``s that mean non-finite values met in a step (the rasteriser's
#: "means must be finite, got NaN or Inf values"): the step is skipped like a NaN loss.
NON_FINITE = re.compile(r"\bfinite\b|\bNaN\b")


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
        set_tf32(c.tf32)
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
        self.optimizer, self.scheduler = optimiser_and_schedule(self.model, c.optimizer,
                                                                c.train.steps)
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
        state = resumable_state(path, self.device, self.config.model.trust_checkpoint)
        check_same_model(path, state, self.model.cfg.to_dict(), self.config)
        check_same_schedule(path, state, self.config)
        load_training_state(path, state, self.model, self.optimizer, self.scheduler)
        self.step, self.skipped = state["step"], state.get("skipped", 0)
        self.depth_range = state.get("depth_range")
        self.saved_step = self.step
        self.step_tracker.set_step(self.step)
        restore_position(path, state, self.batches, self.rank, self.world)
        log.info("resumed from %s at step %d", path, self.step)
        return True

    # -- one step --
    def loss(self, out, batch: dict) -> tuple[torch.Tensor, dict]:
        """MSE on the targets, + LPIPS after ``loss.lpips_after_step``, + the depth terms
        (``loss.depth`` on the context views, ``loss.target_depth`` on the rendered targets;
        until ``loss.depth_until_step``) where the data has depth
        (``usplat_dr.training.losses.training_loss``)."""
        return training_loss(out, batch, self.config.loss, self.step, self.device, self.lpips)

    def train_step(self, batch: dict) -> dict | None:
        """One optimiser step on ``batch``: its statistics, or ``None`` when the loss or
        gradient is not finite, or the forward pass met non-finite values (a ``ValueError``
        matching ``NON_FINITE``, e.g. the rasteriser's "means must be finite"): no update,
        BatchNorm statistics restored; the learning-rate schedule advances as for any step."""
        self.ddp.train()
        args = model_inputs(batch, self.device)
        target = batch["target"]["image"].to(self.device)
        self.depth_range = widened_depth_range(self.depth_range, args.context.near,
                                               args.context.far)
        self.optimizer.zero_grad(set_to_none=True)
        # BatchNorm statistics change in the forward pass: kept to be put back if the step
        # is skipped (a NaN input would otherwise poison them for good)
        buffers = {n: b.detach().clone() for n, b in self.model.named_buffers()}
        budget = step_budget(self.config, self.step)
        try:
            out = self.ddp(*args, global_step=self.step, budget=budget)
            loss, parts = self.loss(out, batch)
            loss.backward()
        except ValueError as e:
            if not NON_FINITE.search(str(e)):
                raise
            if self.world > 1:  # the other ranks wait in this step's collectives: stop all
                raise TrainingStopped(f"step {self.step}: {e}; stopped. "
                                      f"{self.last_good()}") from None
            return self._skip(buffers, f"non-finite values in the forward pass ({e})")
        norm, grad_norms = clip_gradients(self.model, self.config.optimizer.gradient_clip)
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
        if budget is not None:
            parts["budget"] = budget.keep
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
            held.enter_context(signals_caught(self._on_signal))
            held.enter_context(cores_awake(self.config.keep_cores_awake, self.device))
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
            self._val_batch = validation_batch(self.config.dataset, batch)
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
            meter = (view_meter(self.model, self._val_batch, self.device)
                     if validating and logged and last else {})
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

    def validate(self) -> Path | None:
        """A PNG grid of the validation scene (``validation.validation_grid``)."""
        if self._val_batch is None:
            return None
        return validation_grid(self.model, self._val_batch, self.device, self.out, self.step)
