"""Run by tests/training/test_trainer.py under torchrun with 2 processes: one training step,
rank r on example r of the synthetic set; rank 0 saves the averaged, clipped gradients. With a
third argument ``single`` it runs as one plain process on both examples at once (the
reference, in a fresh process like the ranks: the same CPU code paths on both sides)."""

import sys
from pathlib import Path

import torch
from torch.utils.data import default_collate

from tests.training.test_trainer import config, first_examples
from usplat_dr.training import Trainer


def main() -> None:
    root, out = Path(sys.argv[1]), Path(sys.argv[2])
    if sys.argv[3:] == ["single"]:
        trainer = Trainer(config(root, out / "single", 1))
        trainer.train_step(default_collate(first_examples(trainer, 2)))
        grads = {n: p.grad for n, p in trainer.model.named_parameters()}
        torch.save({"grads": grads}, out / "single.pt")
        return
    trainer = Trainer(config(root, out / "ddp", 1))
    example = first_examples(trainer, 2)[trainer.rank]
    trainer.train_step(default_collate([example]))
    if trainer.rank == 0:  # the gradients after DDP's all-reduce and clipping
        grads = {n: p.grad for n, p in trainer.model.named_parameters()}
        torch.save({"grads": grads}, out / "ddp.pt")
    torch.distributed.destroy_process_group()


if __name__ == "__main__":
    main()
