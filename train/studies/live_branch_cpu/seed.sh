#!/usr/bin/env bash
# One more seed of the live arm (E_H = the primary network's features, gate 0.02, the branch
# trained alone from tiny_full at 32 scenes a step; seed 0 is tiny_full_live, trained on a GPU)
# on one CPU core, resumable across machines and days (train/studies/LOG.md, "Seeds of the
# live arm"). About 15 s a step on one core of an AVX-512 host: the step-2,000 checkpoint the
# verdict reads is about 8 hours away.
#
#   nohup bash train/studies/live_branch_cpu/seed.sh 1 > outputs/live/cpu_b32_seed1.log 2>&1 &
#
# Data: the GPU run's own 200 JPEG training scenes (.gpudata, packed from outputs/big/train480
# as below when missing), unpacked into outputs/live/gpudata so that .gpudata stays small
# enough to travel. The run folder is outputs/live/cpu_b32_seed$SEED; where it is missing, the
# state of the last stop is restored first: committed as seed$SEED.ckpt and then removed from
# the working tree (13 MB that would not travel to a GPU machine), the commit that holds it
# named in seed$SEED.commit (its metrics.csv kept as seed${SEED}_metrics.csv).
set -euo pipefail
SEED=${1:?seed (1-4; seed 0 is tiny_full_live)}
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../../.." && pwd)
cd "$ROOT"
PY=${PYTHON:-.venv/bin/python}
HERE=train/studies/live_branch_cpu
RUN=outputs/live/cpu_b32_seed$SEED
DATA=outputs/live/gpudata
if [ ! -d .gpudata/train ]; then
  $PY train/studies/carry_sets.py pack --out .gpudata --jpeg-quality 90 --chroma 420 \
    train=outputs/big/train480/train:200:jpeg heldout=outputs/big/test5000:30:png
fi
if [ ! -d "$DATA/train" ]; then
  mkdir -p "$DATA" && cp -r .gpudata/train .gpudata/heldout "$DATA/"
  $PY train/studies/carry_sets.py unpack "$DATA"
fi
if [ ! -f "$RUN/checkpoints/last.ckpt" ] && [ -f "$HERE/seed$SEED.commit" ]; then
  mkdir -p "$RUN/checkpoints"
  git show "$(cat "$HERE/seed$SEED.commit"):$HERE/seed$SEED.ckpt" > "$RUN/checkpoints/last.ckpt"
  cp "$HERE/seed${SEED}_metrics.csv" "$RUN/metrics.csv"
fi
exec $PY -m usplat_dr train --config synthetic_tiny_depth.yaml "dataset.roots=[$DATA/train]" \
  model.init_from=tiny_full train.trainable=view_specific optimizer.lr=1e-3 \
  model.open_gate_std=0.02 model.overrides.view_features=primary threads=1 seed="$SEED" \
  dataset.overrides.seed="$SEED" train.progress=false train.steps=6000 \
  train.checkpoint_every=25 train.keep_every=250 train.validate_every=500 train.log_every=25 \
  data_loader.batch_size=32 output_dir="$RUN" --resume
