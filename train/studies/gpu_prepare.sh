#!/usr/bin/env bash
# What `bash scripts/run.sh gpu-train` needs on a GPU machine, made here (Mitsuba renders the
# data; the GPU machine has none): the registered 256x256 sets (train/studies/LOG.md, "A GPU
# path to 256x256") rendered with `usplat synth`, packed with carry_sets.py into GPUDATA, and
# the drjit wheel for the GPU machine's Python downloaded into .whl/; then what travels is
# weighed against the 64 MiB a call may carry.
#
#   bash scripts/run.sh gpu-prepare        # here; then, on the GPU machine, with carry
#   bash scripts/run.sh gpu-train OUT      # [".gpudata256", ".whl"]
#
# Environment: SIZE (default 256), DATA (where the sets are rendered, default outputs/big256;
# a set already there with the same stage, scenes, seed, size and frames is kept), GPUDATA
# (default .gpudata256, made anew; an existing folder it did not make is refused, as is a set
# in DATA other than the one asked for: nothing it did not write is deleted), TRAIN_SCENES and HELDOUT_SCENES (default 12 and 8 packed,
# of the 16 and 12 rendered), FRAMES (default 24), JOBS (rendering processes, default 2),
# SYNTH_ARGS (more `usplat synth` arguments), WHEEL (default 1; 0: no wheel, as the CPU test
# does), WHEEL_PYTHON (the GPU machine's Python, default 3.12), LIMIT_MB (what may travel,
# default 67.1, 64 MiB), PYTHON. 4 min 13 s on two AVX-512 cores (2026-11-30), rendering most
# of it.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
cd "$ROOT"
PY=${PYTHON:-python3}
SIZE=${SIZE:-256}
DATA=${DATA:-outputs/big$SIZE}
GPUDATA=${GPUDATA:-.gpudata256}
TRAIN_SCENES=${TRAIN_SCENES:-12}
HELDOUT_SCENES=${HELDOUT_SCENES:-8}
FRAMES=${FRAMES:-24}
JOBS=${JOBS:-2}
# the registered sets: the first 16 training scenes of seed 100 and the first 12 held-out ones
# of seed 5000 (the seed of every held-out set here; nothing trains or chooses on it)
RENDER_TRAIN=$(( TRAIN_SCENES > 16 ? TRAIN_SCENES : 16 ))
RENDER_HELDOUT=$(( HELDOUT_SCENES > 12 ? HELDOUT_SCENES : 12 ))
if [ "$SIZE" != 256 ]; then  # a small trial (the CPU test) renders only what it packs
    RENDER_TRAIN=$TRAIN_SCENES; RENDER_HELDOUT=$HELDOUT_SCENES
fi

# Only folders this script made are replaced (they hold its mark); any other is refused.
MARK=.gpu-prepare
for folder in "$GPUDATA" "$GPUDATA.new"; do
    if [ -e "$folder" ] && [ ! -f "$folder/$MARK" ]; then
        echo "gpu-prepare: GPUDATA $folder exists and is not a pack gpu-prepare made (no" \
            "$MARK in it): move it away, or set GPUDATA to a new folder" >&2
        exit 2
    fi
done

render() {  # FOLDER STAGE SCENES SEED: usplat synth, unless FOLDER's synth.json (written
    local folder=$1 stage=$2 scenes=$3 seed=$4  # last) records this set already
    if $PY - "$folder" "$stage" "$scenes" "$seed" "$SIZE" "$FRAMES" <<'EOF'
import json
import sys

from usplat_dr.data.chunks import metadata_folder

folder, stage, scenes, seed, size, frames = sys.argv[1:]
try:
    made = json.loads((metadata_folder(folder, stage) / "synth.json").read_text())
except (OSError, ValueError):
    sys.exit(1)
wanted = {"stage": stage, "scenes": int(scenes), "seed": int(seed), "frames": int(frames),
          "resolution": [int(size), int(size)]}
sys.exit(any(made.get(k) != v for k, v in wanted.items()))
EOF
    then
        echo "gpu-prepare: $folder is there ($stage, $scenes scenes, seed $seed, ${SIZE}x$SIZE)"
        return
    fi
    if [ -e "$folder" ]; then  # another set (another size, seed or count): never deleted here
        echo "gpu-prepare: $folder holds another set than this one ($stage, $scenes scenes," \
            "seed $seed, ${SIZE}x$SIZE, $FRAMES frames): move it away, or set DATA to" \
            "another folder" >&2
        exit 2
    fi
    $PY -m usplat_dr synth --out "$folder" --stage "$stage" --scenes "$scenes" \
        --frames "$FRAMES" --image-shape "$SIZE" "$SIZE" --seed "$seed" --jobs "$JOBS" \
        ${SYNTH_ARGS:-}
}

render "$DATA/test5000" test "$RENDER_HELDOUT" 5000
render "$DATA/train$RENDER_TRAIN" train "$RENDER_TRAIN" 100

# packed anew into a sibling folder, then swapped in: an interrupted run leaves the old one
rm -rf "$GPUDATA.new"
mkdir -p "$GPUDATA.new"
echo "made by train/studies/gpu_prepare.sh" > "$GPUDATA.new/$MARK"
$PY train/studies/carry_sets.py pack --out "$GPUDATA.new" --jpeg-quality 90 --chroma 420 \
    "train=$DATA/train$RENDER_TRAIN/train:$TRAIN_SCENES:jpeg"
$PY train/studies/carry_sets.py pack --out "$GPUDATA.new" \
    "heldout=$DATA/test5000:$HELDOUT_SCENES:jpeg"
rm -rf "$GPUDATA"
mv "$GPUDATA.new" "$GPUDATA"

if [ "${WHEEL:-1}" != 0 ]; then
    version=$($PY -c 'import drjit; print(drjit.__version__)')
    python=${WHEEL_PYTHON:-3.12}
    if ! ls .whl/drjit-"$version"-cp"${python/./}"-*.whl >/dev/null 2>&1; then
        rm -f .whl/drjit-*.whl  # one version of each: two stop the install there
        $PY -m pip download -q --no-deps --only-binary=:all: --python-version "$python" \
            --implementation cp --platform manylinux_2_28_x86_64 \
            --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
            "drjit==$version" \
            || { echo "gpu-prepare: could not download drjit==$version for Python $python" \
                      "(no network?): put its wheel in .whl/"; exit 1; }
    fi
    ls -l .whl/
fi

# what travels: the tracked files, the wheels, the packed sets
if ! git rev-parse --is-inside-work-tree >/dev/null 2>&1; then
    echo "gpu-prepare: ready, but not in a git checkout: what travels (the tracked files," \
         "$GPUDATA and .whl) is not weighed"
    exit 0
fi
tracked=$(git ls-files -z | xargs -0 stat -c %s | awk '{s += $1} END {print s + 0}')
extra=$(du -sb "$GPUDATA" $([ -d .whl ] && echo .whl) | awk '{s += $1} END {print s + 0}')
awk -v t="$tracked" -v e="$extra" -v limit="${LIMIT_MB:-67.1}" -v packed="$GPUDATA" 'BEGIN {
    printf "gpu-prepare: %.1f MB travel (tracked %.1f; %s and .whl %.1f); the limit: %.1f MB\n",
           (t + e) / 1e6, t / 1e6, packed, e / 1e6, limit
    exit ((t + e) / 1e6 > limit) }' \
    || { echo "gpu-prepare: too much to carry: pack fewer scenes (TRAIN_SCENES, HELDOUT_SCENES)"
         exit 1; }
echo "gpu-prepare: ready; on the GPU machine: bash scripts/run.sh gpu-train OUT" \
     "(carry $GPUDATA and .whl)"
