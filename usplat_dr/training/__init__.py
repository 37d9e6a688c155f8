"""Training: the trainer (``trainer``), the configuration's sections as objects (``config``),
processes and RNG state (``distributed``), checkpoint files and the shipped ones
(``checkpoints``), and per-scene Gaussian optimisation (``per_scene``, ``usplat fit``)."""

from usplat_dr.training.distributed import RankFailed
from usplat_dr.training.trainer import Trainer, TrainingStopped, train

__all__ = ["RankFailed", "Trainer", "TrainingStopped", "train"]
