"""Training: the loop (``trainer``; ``launch.train`` starts a run) and what it is made of: the
run folder, signals and cores a run holds (``run_folder``), the optimiser (``optim``), the batch
stream (``batches``), what a stage trains (``stages``), resuming (``resume``), validation
(``validation``), the run log (``run_log``) and the loss (``losses``); the configuration's
sections as objects (``config``), processes and RNG state (``distributed``), checkpoint files
and the shipped ones (``checkpoints``), the demo's run recipes (``recipes``), and per-scene
Gaussian optimisation (``per_scene``, ``usplat fit``)."""

from usplat_dr.training.distributed import RankFailed
from usplat_dr.training.launch import train
from usplat_dr.training.trainer import Trainer, TrainingStopped

__all__ = ["RankFailed", "Trainer", "TrainingStopped", "train"]
