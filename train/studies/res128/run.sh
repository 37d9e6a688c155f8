#!/usr/bin/env bash
# The primary network (a) at 128x128, fine-tuned from the shipped 64x64 tiny_baseline on the
# same 480 scenes rendered at 128x128, one thread, resumable (train/studies/LOG.md, "Four
# times the pixels: models at 128x128"). About 4x a 64x64 step (0.6-0.7 s on one thread).
#
#   nohup bash train/studies/res128/run.sh > outputs/res128_a.log 2>&1 &
#
# The data (made once, about an hour of one core):
#   usplat synth --out outputs/big128/train480 --stage train --scenes 480 --frames 24 \
#       --image-shape 128 128 --seed 100 --jobs 1
# The first stopping rule (python train/studies/res128/stop_rule.py METRICS) stopped it at step
# 2,000 by chance (its windows' noise is larger than the gain it asks for); by the amendment
# written before it went on, it runs from there to train.steps (15,000), no early stop.
# Where outputs/res128_a is missing, the state of the last stop is restored first: committed as
# train/studies/res128/last.ckpt and then removed from the working tree (it would not travel to
# a GPU machine), the commit that holds it named in train/studies/res128/state.commit; its
# metrics.csv is kept beside them.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../../.." && pwd)
cd "$ROOT"
HERE=train/studies/res128
if [ ! -f outputs/res128_a/checkpoints/last.ckpt ] && [ -f "$HERE/state.commit" ]; then
  mkdir -p outputs/res128_a/checkpoints
  git show "$(cat "$HERE/state.commit"):$HERE/last.ckpt" > outputs/res128_a/checkpoints/last.ckpt
  cp "$HERE/metrics.csv" outputs/res128_a/metrics.csv  # the stopping rule reads every row
fi
exec "${PYTHON:-.venv/bin/python}" -m usplat_dr train --config synthetic_tiny_depth.yaml \
  'dataset.roots=[outputs/big128/train480]' 'dataset.image_shape=[128,128]' \
  model.init_from=tiny_baseline model.variant=baseline threads=1 train.steps=15000 \
  optimizer.lr=2e-4 train.checkpoint_every=250 train.keep_every=1000 train.validate_every=1000 \
  train.progress=false output_dir=outputs/res128_a --resume
