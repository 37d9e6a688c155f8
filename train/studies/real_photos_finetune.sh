#!/usr/bin/env bash
# The fine-tuning of the real-photographs study (train/studies/LOG.md, "Real photographs"):
# (c) from tiny_full and (a) from tiny_baseline at 64x64 on the photographic and diffuse
# appearances of the first 200 seed-100 training scenes, one thread each, side by side.
# Resumable: run it again after a kill (--resume continues each run from its last checkpoint).
set -euo pipefail
STEPS=${STEPS:-3000}
PH=outputs/photo/train200_ph
DIFFUSE=outputs/photo/train200
[ -f "$PH/train/synth.json" ] || usplat synth --out "$PH" --stage train --scenes 200 --frames 24 \
    --image-shape 64 64 --seed 100 --appearance photographic --jobs 1
[ -f "$DIFFUSE/train/synth.json" ] || usplat synth --out "$DIFFUSE" --stage train --scenes 200 \
    --frames 24 --image-shape 64 64 --seed 100 --jobs 1
run() {  # variant, init, output folder, seed
    local resume=()
    [ -f "$3/checkpoints/last.ckpt" ] && resume=(--resume)
    USPLAT_THREADS=1 usplat train --config synthetic_tiny_depth.yaml \
        "dataset.roots=[$PH,$DIFFUSE]" model.variant="$1" model.init_from="$2" threads=1 seed="$4" \
        dataset.overrides.seed="$4" \
        train.steps="$STEPS" optimizer.lr=2e-4 train.checkpoint_every=100 \
        train.validate_every=100000 train.progress=false output_dir="$3" "${resume[@]}"
}
run full tiny_full outputs/photo/ft_full 0 > outputs/photo/ft_full.log 2>&1 &
# (a) is faster: a second seed of (c) follows it on the same core (with init_from the data
# order is all a seed changes, and dataset.overrides.seed sets it: seed= alone gave weights
# identical bit for bit to seed 0's, 2026-12-02)
(run baseline tiny_baseline outputs/photo/ft_baseline 0 > outputs/photo/ft_baseline.log 2>&1
 run full tiny_full outputs/photo/ft_full_seed1 1 > outputs/photo/ft_full_seed1.log 2>&1) &
wait
