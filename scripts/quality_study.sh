#!/usr/bin/env bash
# Map-quality study: train the three kernel variants on one synthetic drive and
# score every kernel on another drive with its own seed and layout.
#
#   scripts/quality_study.sh [OUT=out/quality] [FRAMES=300] [TRAIN_FRAMES=300] [EPOCHS=2] [TEST_SEED=2]
#
# Writes OUT/train (drive, seed 1), OUT/test (drive, seed TEST_SEED), OUT/kernels/*.yaml (+ PNGs)
# and OUT/report.json with the per-class table printed at the end.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
OUT="${1:-out/quality}"
FRAMES="${2:-300}"
TRAIN_FRAMES="${3:-300}"
EPOCHS="${4:-2}"
TEST_SEED="${5:-2}"
PY=.venv/bin/python
mkdir -p "$OUT/kernels"

[[ -d "$OUT/train/sequences/00" ]] || $PY -m convbki_core.tools.synth --out "$OUT/train" --sequence 00 --frames "$TRAIN_FRAMES" --seed 1
[[ -d "$OUT/test/sequences/08" ]] || $PY -m convbki_core.tools.synth --out "$OUT/test" --sequence 08 --frames "$FRAMES" --seed "$TEST_SEED"

for kind in single per_class compound; do
    [[ -f "$OUT/kernels/$kind.yaml" ]] || $PY -m convbki_core.tools.train --dataset "$OUT/train" --sequences 00 \
        --kernel "$kind" --epochs "$EPOCHS" --out "$OUT/kernels/$kind.yaml"
done

$PY -m convbki_core.tools.evaluate --dataset "$OUT/test" --sequence 08 --report "$OUT/report.json" \
    --kernel config/kernels/semantic_kitti_sbki.yaml "$OUT/kernels/single.yaml" "$OUT/kernels/per_class.yaml" \
    "$OUT/kernels/compound.yaml" config/kernels/semantic_kitti_compound.yaml
