"""Training: the trainer (``trainer``), the configuration's sections as objects (``config``),
processes and RNG state (``distributed``), and checkpoint files (``checkpoints``)."""

from usplat_dr.training.distributed import RankFailed
from usplat_dr.training.trainer import Trainer, TrainingStopped, train

__all__ = ["RankFailed", "Trainer", "TrainingStopped", "train"]
