#!/usr/bin/env bash
# From nothing to the shipped keypoint detector. Stage A: render the train look with the built-in
# simulator and train both networks from scratch (models/train.yaml). Stage B: render the looks
# (the `wide` preset, threadless needles, 640x480 with and without lens distortion, the second
# renderer's threaded scenes) and
# train both networks on them from stage A's weights (models/looks.yaml). Stage C: render needles
# the instruments hold, hand over and drive through tissue, and train both networks on them from
# stage B's weights, keeping stage B's outputs on needles at rest (models/held.yaml). Familiarity: the
# training looks' crop descriptors, from six small folders of them that no training stage sees
# (familiarity.json). End identity: fit the coefficients of P(A is the tip) on those folders and
# on a look family no training renders (`liver`, also read hue-turned and colourless), so that
# the fit sees the network on unfamiliar images (end_identity.json). The second renderer's
# threadless needles and the `silicone` pads are never rendered here: they are the held-out looks.
# Prints the wall-clock of each stage.
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

needletrack train --data "$DATA/a" --data "$DATA/b" --data "$DATA/neg" --config "$HERE/train.yaml" --out "$OUT/stage_a"
stamp "stage A trained: $OUT/stage_a/model.pt"

L="$DATA/looks"
gen() { needletrack dataset generate --quiet "$@"; }
# the second renderer (numpy, one core) runs beside the MuJoCo sets
needletrack dataset generate-alt --out "$L/alt" --sequences 150 --steps 2 --seed 8106 --supersample 2 --quiet &
alt=$!
gen --out "$L/std" --sequences 300 --steps 2 --seed 8105 --randomise train --msaa 4
gen --out "$L/std2" --sequences 400 --steps 2 --seed 8109 --randomise train --msaa 0
gen --out "$L/std_none" --sequences 250 --steps 2 --seed 8108 --randomise train --msaa 4 --thread none
gen --out "$L/wide" --sequences 350 --steps 2 --seed 8101 --randomise wide --msaa 0
gen --out "$L/wide_none" --sequences 350 --steps 2 --seed 8102 --randomise wide --msaa 4 --thread none
gen --out "$L/640" --sequences 200 --steps 2 --seed 8103 --randomise wide --width 640 --height 480
gen --out "$L/640_none" --sequences 150 --steps 2 --seed 8104 --randomise wide --width 640 --height 480 --thread none
needletrack dataset distort "$L/640_none" --out "$L/640_none_dist" --dist=-0.28,0.09,0.0005,-0.0004 --quiet
needletrack dataset generate-negatives --out "$L/neg" --frames 200 --seed 8107 --randomise wide --quiet
# familiarity and end-identity folders (fit only, never trained on): the train and test looks,
# `wide`, `wide` threadless, 640x480 both kinds; the `liver` family (a look no training renders)
C="$DATA/end_identity"
gen --out "$C/std" --sequences 40 --steps 2 --seed 8203 --randomise train --msaa 4
gen --out "$C/test" --sequences 40 --steps 2 --seed 8204 --randomise test --msaa 4
gen --out "$C/liver" --sequences 40 --steps 2 --seed 8301 --randomise liver --msaa 4
gen --out "$C/liver_none" --sequences 40 --steps 2 --seed 8302 --randomise liver --msaa 4 --thread none
gen --out "$C/liver640_none" --sequences 40 --steps 2 --seed 8303 --randomise liver --msaa 4 --width 640 --height 480 --thread none
gen --out "$C/wide" --sequences 40 --steps 2 --seed 8201 --randomise wide --msaa 4
gen --out "$C/wide_none" --sequences 40 --steps 2 --seed 8202 --randomise wide --msaa 4 --thread none
gen --out "$C/640" --sequences 40 --steps 2 --seed 9642 --randomise wide --msaa 4 --width 640 --height 480
gen --out "$C/640_none" --sequences 40 --steps 2 --seed 9641 --randomise wide --msaa 4 --width 640 --height 480 --thread none
wait "$alt"
stamp "data: $L done"

needletrack train --init "$OUT/stage_a/model.pt" --data "$L/std" --data "$L/std2" --data "$L/std_none" --data "$L/wide" --data "$L/wide_none" \
    --data "$L/640" --data "$L/640_none_dist" --data "$L/neg" --data "$L/alt" --config "$HERE/looks.yaml" --out "$OUT/stage_b"
stamp "stage B trained: $OUT/stage_b/model.pt"

# Stage C: needles the instruments hold, hand over and drive through tissue (every 6th frame of
# their takes), beside needles at rest of the same looks; stage B's outputs are kept on the
# folders of needles at rest (--teacher: its keypoint heatmaps too, models/held.yaml)
H="$DATA/held"
needletrack dataset generate-alt --out "$H/alt" --sequences 40 --steps 2 --seed 3507 --supersample 2 --quiet &
alt=$!
gen --out "$H/move_train" --sequences 40 --motion mixed --take-every 6 --seed 3501 --randomise train --msaa 4
gen --out "$H/move_wide_none" --sequences 24 --motion mixed --take-every 6 --seed 3502 --randomise wide --thread none --msaa 4
gen --out "$H/static_train" --sequences 150 --steps 2 --seed 3503 --randomise train --msaa 4
gen --out "$H/static_wide_none" --sequences 100 --steps 2 --seed 3504 --randomise wide --thread none --msaa 0
gen --out "$H/move_640" --sequences 16 --motion mixed --take-every 6 --seed 3505 --randomise wide --width 640 --height 480
gen --out "$H/static_640_none" --sequences 80 --steps 2 --seed 3506 --randomise wide --width 640 --height 480 --thread none
needletrack dataset generate-negatives --out "$H/neg" --frames 100 --seed 3508 --randomise wide --quiet
wait "$alt"
stamp "data: $H done"
needletrack train --init "$OUT/stage_b/model.pt" --data "$H/move_train" --data "$H/move_wide_none" --data "$H/static_train" \
    --data "$H/static_wide_none" --data "$H/move_640" --data "$H/static_640_none" --data "$H/alt" --data "$H/neg" \
    --teacher "$H/static_train" --teacher "$H/static_wide_none" --teacher "$H/static_640_none" --teacher "$H/alt" \
    --config "$HERE/held.yaml" --out "$OUT"
stamp "stage C trained: $OUT/model.pt"
needletrack bench familiarity --weights "$OUT/model.pt" --data "$C/std" --data "$C/test" --data "$C/wide" \
    --data "$C/wide_none" --data "$C/640" --data "$C/640_none" --fit "$OUT/familiarity.json"
stamp "familiarity fitted: $OUT/familiarity.json"
needletrack bench end-identity --weights "$OUT/model.pt" --data "$C/std" --data "$C/test" --data "$C/wide" --data "$C/wide_none" \
    --data "$C/640" --data "$C/640_none" --data "$C/liver" --data "$C/liver_none" --data "$C/liver640_none" \
    --hue-data "$C/liver" --hue-data "$C/liver_none" --hue-data "$C/liver640_none" \
    --grey-data "$C/liver" --grey-data "$C/liver_none" --grey-data "$C/liver640_none" --grey-data "$C/wide" \
    --grey-data "$C/wide_none" --fit "$OUT/end_identity.json"
stamp "end identity fitted: $OUT/end_identity.json"
