#!/usr/bin/env bash
# The verdict runs' kept states scored as the verdict reads them (train/studies/LOG.md, "The
# verdict by the paper's protocol with extrapolated targets" and "(c) at 128x128 and the verdict
# there"): each run's step-STOP checkpoint exported as shipped weights (float16, loadable with
# torch.load(weights_only=True)), then `usplat eval` on the held-out splits with one thread.
# Resumable: an export or an evaluation already written is kept.
#
#   OUT=outputs/beyond128 DATA=outputs/big128/test5000 EVAL=train/studies/beyond128 \
#     bash train/studies/beyond_eval.sh full_seed_0 baseline_seed_0
#   -> OUT/NAME/step_0000300.pt, EVAL/eval_NAME/{per_scene.csv,summary.json}, and beside the
#      run OUT/NAME.eval.log and OUT/NAME.renders
#
# Environment: OUT (the runs' folder, default outputs/beyond), STOP (default 300), DATA (the
# held-out set, default outputs/big/test5000), EVAL (default train/studies/beyond), SPLITS
# (default "standard wide_baseline extrapolation"), DRY_RUN=1 (print the commands, run nothing).
# Then `train/studies/live_seeds.py --live-split extrapolation` reads the folders.
set -uo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
cd "$ROOT"
PY=${PYTHON:-.venv/bin/python}
OUT=${OUT:-outputs/beyond}; STOP=${STOP:-300}; DATA=${DATA:-outputs/big/test5000}
EVAL=${EVAL:-train/studies/beyond}; DRY_RUN=${DRY_RUN:-0}
read -r -a splits <<<"${SPLITS:-standard wide_baseline extrapolation}"
[ $# -gt 0 ] || { echo "give the runs, e.g. full_seed_0 baseline_seed_0"; exit 2; }
status=0
for name in "$@"; do
  kept=$(printf "%s/%s/checkpoints/step_%07d.ckpt" "$OUT" "$name" "$STOP")
  weights=$(printf "%s/%s/step_%07d.pt" "$OUT" "$name" "$STOP")
  folder="$EVAL/eval_$name"
  if [ -f "$folder/summary.json" ]; then echo "$name: already scored ($folder)"; continue; fi
  if [ ! -f "$kept" ]; then
    echo "$name: no step-$STOP checkpoint at $kept (train it first: beyond_seeds.sh)"
    status=1; continue
  fi
  export_cmd=("$PY" -c 'import sys; import usplat_dr
from usplat_dr.training.checkpoints import export_weights
export_weights(sys.argv[1], sys.argv[2], half=True)' "$kept" "$weights")
  eval_cmd=("$PY" -m usplat_dr eval --checkpoint "$weights" --data "$DATA"
            --splits "${splits[@]}" --out "$folder")
  if [ "$DRY_RUN" = 1 ]; then
    echo "$name: export $kept -> $weights; USPLAT_THREADS=1 ${eval_cmd[*]}"; continue
  fi
  if [ ! -f "$weights" ]; then
    "${export_cmd[@]}" || { echo "$name: export failed"; status=1; continue; }
  fi
  mkdir -p "$EVAL"
  # the log (progress bars) and the renders beside the run, not in EVAL (which may be
  # committed): EVAL keeps the scores
  if USPLAT_THREADS=1 "${eval_cmd[@]}" >"$OUT/$name.eval.log" 2>&1; then
    if [ -d "$folder/renders" ]; then
      rm -rf "$OUT/$name.renders"; mv "$folder/renders" "$OUT/$name.renders"
    fi
    echo "$name: scored ($folder)"
  else
    echo "$name: evaluation failed (see $OUT/$name.eval.log)"; status=1
  fi
done
exit $status
