"""Run by tests/test_training.py under torchrun with 2 processes: one training step, rank r on
example r of the synthetic set; rank 0 saves the averaged, clipped gradients."""

import sys
from pathlib import Path

import torch
from torch.utils.data import default_collate

from tests.training.test_trainer import config, first_examples
from usplat_dr.training import Trainer


def main() -> None:
    root, out = Path(sys.argv[1]), Path(sys.argv[2])
    trainer = Trainer(config(root, out / "ddp", 1))
    example = first_examples(trainer, 2)[trainer.rank]
    trainer.train_step(default_collate([example]))
    if trainer.rank == 0:  # the gradients after DDP's all-reduce and clipping
        grads = {n: p.grad for n, p in trainer.model.named_parameters()}
        torch.save({"grads": grads}, out / "ddp.pt")
    torch.distributed.destroy_process_group()


if __name__ == "__main__":
    main()
