#!/usr/bin/env bash
# The primary network (a) one octave up, on one GPU: fine-tunes a model trained at half the size
# (INIT, default the shipped tiny_baseline_128) at SIZE x SIZE (default 256) on a synthetic set
# packed here by carry_sets.py (Mitsuba need not be there), for SECONDS of training, then scores
# it on the carried held-out set against INIT's renders upsampled 2x (res128_eval.py --size),
# and brings back its whole state, a shippable .pt and the scores (train/studies/LOG.md,
# "Four times the pixels").
#
#   bash scripts/run.sh gpu-prepare     # here: renders and packs .gpudata256, fetches .whl
#   bash scripts/run.sh gpu-train OUT [SECONDS] [STEPS]     # on the GPU machine
#
# gpu-prepare (train/studies/gpu_prepare.sh) packs the registered sets as
#   python train/studies/carry_sets.py pack --out .gpudata256 --jpeg-quality 90 --chroma 420 \
#       train=outputs/big256/train16/train:12:jpeg
#   python train/studies/carry_sets.py pack --out .gpudata256 heldout=outputs/big256/test5000:8:jpeg
#
# SECONDS (default 300): the training's wall-time limit (it stops at STEPS, default 100000, or
# at the limit; its state is written every CHECKPOINT_EVERY steps, default 50, and the last one
# is what is scored). Writes OUT/last.ckpt (weights and optimiser: `usplat train ... --resume`
# goes on from it anywhere), OUT/model.pt (`export_weights`: float16, loadable with
# weights_only=True), OUT/train.log, OUT/metrics.csv, and OUT/eval/ (summary.json,
# per_scene.csv, comparison.png). Environment: INIT (a shipped name or a checkpoint), SIZE,
# BATCH (default 8), LR (default 2e-4), GPUDATA (default .gpudata256), WORK (the run's folder;
# a later call with the same WORK on the same machine resumes it), HELDOUT_SCENES (default
# all carried), DEVICE (cuda; cpu tries the script at a tiny size: tests/train/
# test_gpu_train.py), PYTHON.
set -uo pipefail
OUT=${1:?OUT folder}; SECONDS_TRAIN=${2:-300}; STEPS=${3:-100000}
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
cd "$ROOT"
PY=${PYTHON:-python3}
DEVICE=${DEVICE:-cuda}
SIZE=${SIZE:-256}
INIT=${INIT:-tiny_baseline_128}
WORK=${WORK:-/tmp/usplat_gpu_train}
DATA=${GPUDATA:-.gpudata256}
mkdir -p "$OUT" "$WORK"
OUT=$(cd "$OUT" && pwd)
[ -d "$DATA/train" ] && [ -d "$DATA/heldout" ] \
  || { echo "gpu-train: $DATA/train and $DATA/heldout are missing: pack them with" \
            "bash scripts/run.sh gpu-prepare (see the top of $0)"; exit 2; }
$PY train/studies/carry_sets.py unpack "$DATA" || exit 1
start=$(date +%s)
timeout -s INT "$SECONDS_TRAIN" $PY -m usplat_dr train --config synthetic_tiny_depth.yaml \
  "dataset.roots=[$DATA/train]" "dataset.image_shape=[$SIZE,$SIZE]" \
  model.init_from="$INIT" model.variant=baseline device="$DEVICE" threads=1 \
  optimizer.lr="${LR:-2e-4}" data_loader.batch_size="${BATCH:-8}" train.steps="$STEPS" \
  train.checkpoint_every="${CHECKPOINT_EVERY:-50}" train.keep_every=0 \
  train.validate_every=1000000 train.log_every=25 train.progress=false \
  output_dir="$WORK/run" --resume >"$WORK/train.log" 2>&1
code=$?
echo "training: $(( $(date +%s) - start )) s (exit $code; 124 or 130: the time limit)"
grep '"step"' "$WORK/train.log" | tail -n 2 | cut -c1-300
grep -i "error\|Traceback" "$WORK/train.log" | head -n 5
cp "$WORK/train.log" "$OUT/train.log"
[ -f "$WORK/run/metrics.csv" ] && cp "$WORK/run/metrics.csv" "$OUT/metrics.csv"
STATE=$WORK/run/checkpoints/last.ckpt
[ -f "$STATE" ] || { echo "gpu-train: no checkpoint was written (see $OUT/train.log)"; exit 1; }
cp "$STATE" "$OUT/last.ckpt"
$PY -c 'import sys; from usplat_dr.training.checkpoints import export_weights
export_weights(sys.argv[1], sys.argv[2])' "$STATE" "$OUT/model.pt" || exit 1
scenes=()
[ -n "${HELDOUT_SCENES:-}" ] && scenes=(--scenes "$HELDOUT_SCENES")
$PY train/studies/res128_eval.py --size "$SIZE" --model-large "$OUT/model.pt" \
  --model-small "$INIT" --data "$DATA/heldout" --device "$DEVICE" "${scenes[@]}" \
  --out "$OUT/eval" 2>&1 | grep -v "jit_find_library\|jitc_llvm_init" | tail -n 6
echo "total: $(( $(date +%s) - start )) s"
