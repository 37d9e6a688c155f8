#!/usr/bin/env bash
# The live-branch arms at a scale one CPU core cannot reach: several training runs side by side
# on one GPU for a fixed wall time each, then the view-specificity meter of every run's last
# checkpoint on training and held-out scenes (train/studies/LOG.md, "A live view-specific
# branch"). Data: sets packed here by carry_sets.py (Mitsuba need not be there).
#
#   python train/studies/carry_sets.py pack --out .gpudata \
#       train=outputs/big/train480/train:150:jpeg heldout=outputs/big/test5000:30:png
#
# (The run of 2026-11-27 carried 200 training scenes packed with --jpeg-quality 90 --chroma 420.)
#   bash train/studies/live_branch_gpu.sh OUT [SECONDS] [STEPS] [DEVICE]
#
# SECONDS (default 240): each run's wall-time limit (it stops at STEPS or at the limit; its last
# checkpoint, written every 50 steps, is what the meter reads; every 250th step's is kept, and
# the one at step 750 is read on the held-out scenes too, to compare arms at equal steps).
# DEVICE: cuda (default), or cpu to try the script at a tiny size (tests/train/
# test_live_branch_gpu.py: BATCH=2, GPUDATA=another packed folder). Writes OUT/results.tar.gz
# (each run's log and metrics.csv, the meter's meter.csv and meter.json) and each run's whole
# last state as OUT/NAME.ckpt (weights and optimiser: `usplat train ... --resume` continues it
# anywhere, `export_weights` makes a shipped-style .pt of it; about 13 MB each).
# Environment: ARMS (the arms to run), SEED or SEEDS ("1 2": each arm once per seed, side by
# side, runs named ARM_sN), KEEP_BACK ("2000": those steps' kept checkpoints come back as
# OUT/RUN_step2000.ckpt), KEEP_EVERY (default 250), CHECKPOINT_EVERY (default 50), WORK (the
# runs' folder: a later call with the same WORK on the same machine resumes them;
# RESUME_ONLY=1: stop unless every run has a state there), METER (0: no meter at the end),
# BATCH, GPUDATA, PYTHON.
set -uo pipefail
OUT=${1:?OUT folder}; SECONDS_EACH=${2:-240}; STEPS=${3:-6000}; DEVICE=${4:-cuda}
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
cd "$ROOT"
PY=${PYTHON:-python3}
WORK=${WORK:-/tmp/live_branch_gpu}
mkdir -p "$OUT" "$WORK"
DATA=${GPUDATA:-.gpudata}  # the packed sets (another folder: a test on the CPU)
$PY train/studies/carry_sets.py unpack "$DATA" || exit 1
BATCH=${BATCH:-16}
SEED=${SEED:-0}  # the runs' seed (model noise and data order); seeds of one arm: SEED=1 ...
# SEEDS: several seeds of each arm side by side ("1 2"); each run is then named ARM_sN
SEEDS=${SEEDS:-$SEED}
# KEEP_BACK: steps whose kept checkpoints come back too, as OUT/RUN_stepN.ckpt ("2000")
KEEP_BACK=${KEEP_BACK:-}
common=(--config synthetic_tiny_depth.yaml "dataset.roots=[$DATA/train]" device=$DEVICE
        threads=1 train.progress=false train.steps=$STEPS train.checkpoint_every=${CHECKPOINT_EVERY:-50}
        train.keep_every=${KEEP_EVERY:-250} train.validate_every=500 train.log_every=50 data_loader.batch_size=$BATCH)
branch=(model.init_from=tiny_full train.trainable=view_specific optimizer.lr=1e-3)
declare -A arms=(
  [branch_gate0]="${branch[*]} model.open_gate_std=0"
  [branch_gate02_h128]="${branch[*]} model.open_gate_std=0.02 model.overrides.specific_hidden=128"
  [branch_primary]="${branch[*]} model.open_gate_std=0.02 model.overrides.view_features=primary"
  [branch_primary_ieee]="${branch[*]} model.open_gate_std=0.02 model.overrides.view_features=primary
                         tf32=false"
  [branch_primary_b32]="${branch[*]} model.open_gate_std=0.02 model.overrides.view_features=primary
                        data_loader.batch_size=$((BATCH * 2))"
  [branch_primary_b32_beyond]="${branch[*]} model.open_gate_std=0.02
                               model.overrides.view_features=primary
                               data_loader.batch_size=$((BATCH * 2))
                               dataset.view_sampler.max_distance_beyond_context_views=4"
  [joint]="model.variant=full model.init_from=tiny_baseline optimizer.lr=2e-4
           optimizer.warm_up_fraction=0.05 optimizer.hyper_lr_scale=10
           model.overrides.delta_init_std=0.01 model.overrides.delta_rank=16
           data_loader.batch_size=$((BATCH / 2))"
)
# ARMS (default: all of them): the names of the arms to run, e.g. ARMS="branch_primary"
if [ -n "${ARMS:-}" ]; then
  for name in "${!arms[@]}"; do [[ " $ARMS " == *" $name "* ]] || unset "arms[$name]"; done
fi
declare -A runs_of=()  # run name -> "arm seed"
read -r -a seed_list <<<"$SEEDS"
for name in "${!arms[@]}"; do
  for seed in "${seed_list[@]}"; do
    run=$name; [ ${#seed_list[@]} -gt 1 ] && run=${name}_s$seed
    runs_of[$run]="$name $seed"
  done
done
if [ "${RESUME_ONLY:-0}" = 1 ]; then  # a continuation: every run must have a state in WORK
  for run in "${!runs_of[@]}"; do
    [ -f "$WORK/$run/checkpoints/last.ckpt" ] || { echo "no state to resume: $WORK/$run"; exit 3; }
  done
fi
start=$(date +%s)
for run in "${!runs_of[@]}"; do
  read -r name seed <<<"${runs_of[$run]}"
  # shellcheck disable=SC2086  # the arm's overrides are words
  timeout -s INT "$SECONDS_EACH" $PY -m usplat_dr train "${common[@]}" ${arms[$name]} \
    seed="$seed" dataset.overrides.seed="$seed" output_dir="$WORK/$run" --resume \
    >"$WORK/$run.log" 2>&1 &
done
wait
echo "training: $(( $(date +%s) - start )) s"
for name in "${!runs_of[@]}"; do
  echo "== $name: $(grep -c '"step"' "$WORK/$name.log") log lines"
  grep '"step"' "$WORK/$name.log" | tail -n 1 | cut -c1-300
  grep -i "error\|Traceback" "$WORK/$name.log" | head -n 5
done
runs=()
for name in "${!runs_of[@]}"; do
  [ -f "$WORK/$name/checkpoints/last.ckpt" ] && runs+=("$WORK/$name")
done
METER=${METER:-1}  # 0: no meter here (the states come back; meter them elsewhere)
if [ "$METER" = 1 ]; then
  $PY train/studies/branch_meter.py --device "$DEVICE" --checkpoints tiny_full "${runs[@]}" \
    --sets train="$DATA/train/train:30" heldout="$DATA/heldout:30" --embedding \
    --out "$WORK/meter" 2>&1 | grep -v "jit_find_library\|jitc_llvm_init"
fi
at750=()
for run in "${runs[@]}"; do
  [ -f "$run/checkpoints/step_0000750.ckpt" ] && at750+=("$run/checkpoints/step_0000750.ckpt")
done
if [ "$METER" = 1 ] && [ ${#at750[@]} -gt 0 ]; then
  $PY train/studies/branch_meter.py --device "$DEVICE" --checkpoints "${at750[@]}" \
    --sets heldout="$DATA/heldout:30" --out "$WORK/meter_750" 2>&1 \
    | grep -v "jit_find_library\|jitc_llvm_init"
fi
for run in "${runs[@]}"; do  # every run's whole state comes back (a fresh machine has none)
  cp "$run/checkpoints/last.ckpt" "$OUT/$(basename "$run").ckpt"
  for step in $KEEP_BACK; do
    kept=$(printf "%s/checkpoints/step_%07d.ckpt" "$run" "$step")
    [ -f "$kept" ] && cp "$kept" "$OUT/$(basename "$run")_step$step.ckpt"
  done
done
tar -czf "$OUT/results.tar.gz" -C "$WORK" --exclude='*.ckpt' --exclude=roots .
echo "total: $(( $(date +%s) - start )) s"

