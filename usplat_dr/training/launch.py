"""``train()``: one training run from a config, as ``usplat train`` starts it (on one process or
every rank under ``torchrun``)."""

import logging
import os

import torch.distributed as dist

from usplat_dr.config import ConfigError
from usplat_dr.training.config import RootCfg
from usplat_dr.training.distributed import rank_failure
from usplat_dr.training.trainer import Trainer, TrainingStopped

log = logging.getLogger(__name__)


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
