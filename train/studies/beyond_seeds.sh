#!/usr/bin/env bash
# The verdict with extrapolated targets (train/studies/LOG.md, "The verdict with
# extrapolated targets"): the live arm's recipe at 8 scenes a step with targets up to 4 frames
# beyond the context views, one run per seed, one thread each, JOBS at a time, each stopped
# (SIGINT: it saves) once its step-STOP checkpoint is kept; the schedule stays the 6,000-step
# one. Resumable: a run folder that exists is resumed.
#
#   JOBS=2 bash train/studies/beyond_seeds.sh 0 2 3 4      # -> outputs/beyond/seed_N
#
# Environment: OUT (default outputs/beyond), STOP (default 300), BEYOND (default 4; 0 runs the
# field's sampler, the control), DATA (default outputs/big/train480), JOBS (default 2), ARM
# (branch, the default: the view-specific branch alone from tiny_full; or baseline: all of
# tiny_baseline trained the same way at peak lr 2e-4, the control (a), runs named
# baseline_seed_N; or full: the paper's protocol, (c) from tiny_baseline with every weight
# trained and its hypernetworks' outputs starting at zero, runs named full_seed_N), INIT (the
# baseline and full arms' start, default tiny_baseline; the 128x128 verdict's: the 128x128 (a)),
# IMAGE_SHAPE ("H W", default the data's config: 64 64), KEEP (the steps between kept
# checkpoints, default 100; STOP must be a multiple), CKPT_EVERY (between checkpoints, default
# 50; a divisor of KEEP), DRY_RUN=1 (print each seed's command, run nothing).
set -uo pipefail
# glibc gives every freed block above its mmap threshold (at most 32 MiB) back to the system,
# and at 8 scenes a step of 128x128 many tensors are larger, so each step faults their pages
# in again. Kept in the heap, a (c) step at 128x128 ran 1.33x faster with the same
# weights bit for bit (train/bench/README.md, "glibc's allocator and a training step"). A
# caller's own setting wins; glibc reads these at start, so they are set here, not in Python.
export MALLOC_MMAP_THRESHOLD_=${MALLOC_MMAP_THRESHOLD_:-4294967296}
export MALLOC_TRIM_THRESHOLD_=${MALLOC_TRIM_THRESHOLD_:-4294967296}
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
cd "$ROOT"
PY=${PYTHON:-.venv/bin/python}
OUT=${OUT:-outputs/beyond}; STOP=${STOP:-300}; BEYOND=${BEYOND:-4}
KEEP=${KEEP:-100}; CKPT_EVERY=${CKPT_EVERY:-50}
DATA=${DATA:-outputs/big/train480}; JOBS=${JOBS:-2}; ARM=${ARM:-branch}
INIT=${INIT:-tiny_baseline}; IMAGE_SHAPE=${IMAGE_SHAPE:-}; DRY_RUN=${DRY_RUN:-0}
shape=()
if [ -n "$IMAGE_SHAPE" ]; then
  read -r h w extra <<<"$IMAGE_SHAPE"
  [[ "$h" =~ ^[0-9]+$ && "$w" =~ ^[0-9]+$ && -z "${extra:-}" ]] || {
    echo "IMAGE_SHAPE must be two numbers, H W (e.g. \"128 128\"), got '$IMAGE_SHAPE'"; exit 2; }
  shape=("dataset.image_shape=[$h,$w]")
fi
case $ARM in
  branch) arm=(model.init_from=tiny_full train.trainable=view_specific optimizer.lr=1e-3
               model.open_gate_std=0.02 model.overrides.view_features=primary); prefix=seed ;;
  baseline) arm=(model.init_from="$INIT" model.variant=baseline optimizer.lr=2e-4)
            prefix=baseline_seed ;;
  full) arm=(model.init_from="$INIT" model.variant=full optimizer.lr=2e-4)
        prefix=full_seed ;;
  *) echo "ARM must be branch, baseline or full, got $ARM"; exit 2 ;;
esac
[ $# -gt 0 ] || { echo "give the seeds, e.g. 0 2 3 4"; exit 2; }
mkdir -p "$OUT"
run_seed() {
  local seed=$1 dir="$OUT/${prefix}_$1"
  local kept
  kept=$(printf "%s/checkpoints/step_%07d.ckpt" "$dir" "$STOP")
  [ -f "$kept" ] && { echo "seed $seed: step $STOP already kept"; return 0; }
  local cmd=("$PY" -m usplat_dr train --config synthetic_tiny_depth.yaml "dataset.roots=[$DATA]"
    "${shape[@]}" device=cpu threads=1 seed="$seed" dataset.overrides.seed="$seed"
    train.progress=false train.steps=6000 train.checkpoint_every="$CKPT_EVERY" train.keep_every="$KEEP"
    train.validate_every=100 train.log_every=10 data_loader.batch_size=8 "${arm[@]}"
    dataset.view_sampler.max_distance_beyond_context_views="$BEYOND" output_dir="$dir" --resume)
  if [ "$DRY_RUN" = 1 ]; then
    echo "seed $seed: MALLOC_MMAP_THRESHOLD_=$MALLOC_MMAP_THRESHOLD_" \
      "MALLOC_TRIM_THRESHOLD_=$MALLOC_TRIM_THRESHOLD_ ${cmd[*]}"
    return 0
  fi
  "${cmd[@]}" >>"$dir.log" 2>&1 &
  local pid=$!
  while kill -0 "$pid" 2>/dev/null && [ ! -f "$kept" ]; do sleep 5; done
  kill -INT "$pid" 2>/dev/null
  wait "$pid"
  [ -f "$kept" ] && echo "seed $seed: step $STOP kept ($kept)" || {
    echo "seed $seed: stopped before step $STOP (see $dir.log)"; return 1; }
}
status=0
for seed in "$@"; do
  while [ "$(jobs -rp | wc -l)" -ge "$JOBS" ]; do wait -n || status=1; done
  run_seed "$seed" &
done
while [ "$(jobs -rp | wc -l)" -gt 0 ]; do wait -n || status=1; done
exit $status
