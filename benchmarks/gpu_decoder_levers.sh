#!/usr/bin/env bash
# The decoder levers that need a GPU, as one unattended run: does a decoder keep the objects that the shipped
# 8x autoencoder loses? (docs/research/first_frame_decoder.md)
#
#   benchmarks/gpu_decoder_levers.sh OUT
#
# Steps, each logged to OUT/log.txt and timed:
#   0. install check: torch sees a CUDA GPU, the project and its model stack import; with no datasets given,
#      ManiSkill must import too (datagen); the GPU, torch, CUDA and CPU are printed;
#   1. data: the held-out sets of the research page (32 tabletop + 16 cube-task episodes, seeds 100000+) and a
#      training set (TRAIN_SCENES tabletop scenes x 4 instructions + TRAIN_CUBES per cube task, seeds 0+), written
#      by `tesseract4d datagen` over Ray on the machine's cores, unless TRAIN / HELDOUT name existing folders;
#   2. lever A, a 4x autoencoder (preset ae-f4c8: 32x32x8 latents, as many numbers as the shipped 16x16x32) from
#      scratch for AE_MINUTES (`train-autoencoder --max-steps auto`: the cosine decay fitted to the budget);
#   3. lever B, the first-frame path on the shipped decoder (attention+copy, the lost-object loss, decoder frozen),
#      PATH_STEPS steps of 16 clips x 8 frames (its cosine decay ends there), stopped after PATH_MINUTES at the latest;
#   4. the ceiling per situation of the shipped decoder, A and B on both held-out sets (measure_ceiling.py, with
#      truth/old/A/B strips of three episodes), written to OUT/ceiling/ceiling.md.
# A transformer on lever A's latents needs a latent preset of 32x32 latents (patch 4 keeps today's 1,024 tokens);
# train one only if A's ceiling clears the goals (object permanence >= 0.95 on both sets).
#
# Environment (all optional): TRAIN, HELDOUT (space-separated dataset folders), AE_MINUTES (default 6),
# PATH_MINUTES (default 3), PATH_STEPS (default 2000), TRAIN_SCENES (default 48), TRAIN_CUBES (default 24), WORKERS
# (default: all cores), PYTHON (default .venv/bin/python), ALLOW_CPU=1 (a smoke run of the script on a machine
# without a GPU, with tiny budgets). Outputs: OUT/{log.txt, data/, ae_f4/, ffpath/, ceiling/}.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
if [ $# -ne 1 ]; then
    echo "usage: benchmarks/gpu_decoder_levers.sh OUT   (see the header for the environment variables)" >&2
    exit 2
fi
OUT="$(realpath -m "$1")"
if [ -e "$OUT" ] && [ -n "$(ls -A "$OUT")" ]; then
    echo "$OUT exists and is not empty; give a new folder (this script writes only into its own)" >&2
    exit 2
fi
mkdir -p "$OUT"
PYTHON="${PYTHON:-.venv/bin/python}"
AE_MINUTES="${AE_MINUTES:-6}"
PATH_MINUTES="${PATH_MINUTES:-3}"
PATH_STEPS="${PATH_STEPS:-2000}"
TRAIN_SCENES="${TRAIN_SCENES:-48}"
TRAIN_CUBES="${TRAIN_CUBES:-24}"
WORKERS="${WORKERS:-$(nproc)}"
SHIPPED=tesseract4d/checkpoints/v2/autoencoder
export PYTHONPATH="$ROOT" OMP_WAIT_POLICY=PASSIVE PYTHONUNBUFFERED=1 HF_HUB_OFFLINE=1
exec > >(tee -a "$OUT/log.txt") 2>&1
step() { echo; echo "== $(date -u +%H:%M:%S) $*"; }

step "0. install check"
if [ ! -x "$PYTHON" ]; then
    echo "no Python at $PYTHON: run scripts/setup.sh first (or set PYTHON to the project's interpreter)"; exit 1
fi
if command -v nvidia-smi >/dev/null; then nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv; fi
ALLOW_CPU="${ALLOW_CPU:-0}" "$PYTHON" - <<'EOF'
import os
import platform
import torch
if not torch.cuda.is_available() and os.environ["ALLOW_CPU"] != "1":
    raise SystemExit("torch sees no CUDA GPU: install a CUDA build of torch (scripts/setup.sh installs the CPU "
                     "one) or run on a GPU machine; CUDA_VISIBLE_DEVICES must not be empty")
import diffusers, tesseract4d  # noqa: F401  (the model stack the runs below load)
gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU (ALLOW_CPU=1)"
print(f"torch {torch.__version__} cuda {torch.version.cuda} on {gpu}; "
      f"diffusers {diffusers.__version__}; CPU {platform.processor() or platform.machine()}")
EOF
if [ -z "${TRAIN:-}" ] || [ -z "${HELDOUT:-}" ]; then
    "$PYTHON" -c "import mani_skill, sapien" || {
        echo "ManiSkill/SAPIEN do not import, so no datasets can be written here: install them (scripts/setup.sh)" \
             "or pass TRAIN and HELDOUT folders written elsewhere by tesseract4d datagen"; exit 1; }
fi

step "1. data"
T4D="$PYTHON -m tesseract4d.cli"
if [ -z "${HELDOUT:-}" ]; then
    $T4D datagen --tasks Tesseract4dTabletop-v1 --instructions-per-scene 4 --episodes 8 --seed-start 100000 \
        --instruction-split heldout --resolution 128 --frames 16 --cameras close --workers "$WORKERS" --quiet \
        --out "$OUT/data/heldout_tabletop"
    $T4D datagen --tasks PickCube-v1,PushCube-v1,StackCube-v1,PullCube-v1 --episodes 4 --seed-start 100000 \
        --instruction-split heldout --resolution 128 --frames 16 --cameras close --workers "$WORKERS" --quiet \
        --out "$OUT/data/heldout_cubes"
    HELDOUT="$OUT/data/heldout_tabletop $OUT/data/heldout_cubes"
fi
if [ -z "${TRAIN:-}" ]; then
    $T4D datagen --tasks Tesseract4dTabletop-v1 --instructions-per-scene 4 --episodes "$TRAIN_SCENES" --seed-start 0 \
        --resolution 128 --frames 16 --cameras close --workers "$WORKERS" --quiet --out "$OUT/data/train_tabletop"
    $T4D datagen --tasks PickCube-v1,PushCube-v1,StackCube-v1,PullCube-v1 --episodes "$TRAIN_CUBES" --seed-start 0 \
        --resolution 128 --frames 16 --cameras close --workers "$WORKERS" --quiet --out "$OUT/data/train_cubes"
    TRAIN="$OUT/data/train_tabletop $OUT/data/train_cubes"
fi
read -r -a TRAIN_DIRS <<< "$TRAIN"
read -r -a HELDOUT_DIRS <<< "$HELDOUT"

step "2. lever A: a 4x autoencoder (ae-f4c8) for $AE_MINUTES minutes"
$T4D train-autoencoder --set preset=ae-f4c8 --data "${TRAIN_DIRS[@]}" --heldout "${HELDOUT_DIRS[0]}" \
    --max-steps auto --max-minutes "$AE_MINUTES" --quiet --out "$OUT/ae_f4"

step "3. lever B: the first-frame path on the shipped decoder, $PATH_STEPS steps or $PATH_MINUTES minutes"
"$PYTHON" -m tesseract4d.model.first_frame_decoder_training --data "${TRAIN_DIRS[@]}" --out "$OUT/ffpath" \
    --injection attention+copy --permanence-loss 2 --min-frame 0 --clips-per-step 16 --frames-per-clip 8 \
    --max-steps "$PATH_STEPS" --max-minutes "$PATH_MINUTES" --ckpt-every 500

step "4. the ceiling per situation: shipped (old), A (f4), B (ffpath)"
"$PYTHON" benchmarks/measure_ceiling.py --autoencoder old="$SHIPPED" --autoencoder f4="$OUT/ae_f4/autoencoder" \
    --autoencoder ffpath="$OUT/ffpath/autoencoder" --data "${HELDOUT_DIRS[@]}" --out "$OUT/ceiling" \
    --strips Tesseract4dTabletop-v1/seed_100002_k0 Tesseract4dTabletop-v1/seed_100000_k1 PullCube-v1/seed_100000
step "done: $OUT/ceiling/ceiling.md"
