#!/usr/bin/env bash
# The primary-features arm (E_H = the primary network's features, gate 0.02) at batch 16 on
# one CPU core, resumable across machines (train/studies/LOG.md, "The primary-features arm
# at batch 16 on one CPU core"). The run folder is outputs/live/cpu_primary_b16; where it is
# missing, it starts from the run's state at its last stop (step 788, optimiser included), kept
# in the repository's history (commit a6aca56, train/studies/live_branch_cpu/last.ckpt; 13 MB,
# out of the working tree so that the tree stays small enough to travel to a GPU machine), so
# the run goes on where it stopped.
#
#   nohup bash train/studies/live_branch_cpu/run.sh > outputs/live/cpu_b16.log 2>&1 &
#   python train/studies/branch_meter.py --checkpoints outputs/live/cpu_primary_b16/checkpoints/step_0001000.ckpt \
#       --sets train=outputs/big/train480/train:30 heldout=outputs/big/test5000:30 --threads 1 \
#       --out outputs/live/meter_b16_1000
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../../.." && pwd)
cd "$ROOT"
HERE=train/studies/live_branch_cpu
RUN=outputs/live/cpu_primary_b16
if [ ! -f "$RUN/checkpoints/last.ckpt" ]; then
  mkdir -p "$RUN/checkpoints"
  git show "a6aca56:$HERE/last.ckpt" > "$RUN/checkpoints/last.ckpt"
  cp "$HERE/metrics.csv" "$RUN/metrics.csv"
fi
exec "${PYTHON:-.venv/bin/python}" -m usplat_dr train --config synthetic_tiny_depth.yaml \
  'dataset.roots=[outputs/big/train480]' model.init_from=tiny_full \
  train.trainable=view_specific optimizer.lr=1e-3 model.open_gate_std=0.02 \
  model.overrides.view_features=primary threads=1 seed=0 train.progress=false \
  train.steps=6000 train.checkpoint_every=25 train.keep_every=250 train.validate_every=250 \
  train.log_every=25 data_loader.batch_size=16 dataset.overrides.seed=0 output_dir="$RUN" --resume
