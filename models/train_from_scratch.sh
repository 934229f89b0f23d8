#!/usr/bin/env bash
# From nothing to the shipped keypoint detector: render the training data with the
# built-in simulator, then train both networks in one run. Prints the wall-clock of each stage.
#   bash models/train_from_scratch.sh [DATA_DIR=data/train] [OUT=models/keypoint]
# Resumable: rerun the same command (the generators and the trainer pick up where they stopped).
set -euo pipefail
DATA=${1:-data/train}
OUT=${2:-models/keypoint}
HERE=$(cd "$(dirname "$0")" && pwd)
t0=$(date +%s)
stamp() { echo "[$(( $(date +%s) - t0 )) s] $*"; }

# needle-free frames (one process) render beside the two needle sets (two processes each)
stamp "data: rendering into $DATA"
needletrack dataset generate-negatives --out "$DATA/neg" --frames 400 --seed 7373 --randomise train --quiet &
neg=$!
needletrack dataset generate --out "$DATA/a" --sequences 1000 --steps 2 --seed 7171 --randomise train --msaa 0 --quiet
stamp "data: $DATA/a done"
needletrack dataset generate --out "$DATA/b" --sequences 500 --steps 2 --seed 7272 --randomise train --msaa 4 --quiet
stamp "data: $DATA/b done"
wait "$neg"
stamp "data: $DATA/neg done"

needletrack train --data "$DATA/a" --data "$DATA/b" --data "$DATA/neg" --config "$HERE/train.yaml" --out "$OUT"
stamp "trained: $OUT/model.pt"
