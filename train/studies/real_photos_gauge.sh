#!/usr/bin/env bash
# The gauge runs of the real-photographs study (train/studies/LOG.md, "The gauge"): (c)
# fine-tuned from tiny_full at 64x64 on the diffuse appearance of the first 200 seed-100
# training scenes, in the baseline gauge and, as its control, in the world gauge, the same in
# everything else, one thread each, side by side. Resumable: run it again after a kill.
set -euo pipefail
STEPS=${STEPS:-3000}
DIFFUSE=outputs/photo/train200
[ -f "$DIFFUSE/train/synth.json" ] || usplat synth --out "$DIFFUSE" --stage train --scenes 200 \
    --frames 24 --image-shape 64 64 --seed 100 --jobs 1
run() {  # gauge, output folder
    local resume=()
    [ -f "$2/checkpoints/last.ckpt" ] && resume=(--resume)
    USPLAT_THREADS=1 usplat train --config synthetic_tiny_depth.yaml \
        "dataset.roots=[$DIFFUSE]" model.variant=full model.init_from=tiny_full \
        model.overrides.gauge="$1" threads=1 seed=0 dataset.overrides.seed=0 \
        train.steps="$STEPS" optimizer.lr=2e-4 train.checkpoint_every=100 \
        train.validate_every=100000 train.progress=false output_dir="$2" "${resume[@]}"
}
run baseline outputs/photo/ft_gauge > outputs/photo/ft_gauge.log 2>&1 &
run world outputs/photo/ft_world > outputs/photo/ft_world.log 2>&1 &
wait
