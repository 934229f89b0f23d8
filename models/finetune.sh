#!/usr/bin/env bash
# Adapt the shipped detector to your scene: fine-tune it on your own dataset folder(s), then score
# the shipped and the fine-tuned weights on a test folder of the same look that training never saw
# (a score already in OUT/eval_before or OUT/eval_after is kept).
#   bash models/finetune.sh OUT TEST_DIR TRAIN_DIR [TRAIN_DIR ...]
# e.g. 400 stereo frames recorded in your simulator (needletrack dataset from-bag ...) in TRAIN_DIR
# and other sequences in TEST_DIR. Takes at most ~20 min on 2 CPU cores (models/finetune.yaml:
# a 15-minute schedule); resumable (rerun the same command). Then use OUT/model.pt as the
# detector's `weights` (dataflow.yaml) or `needletrack eval --model OUT/model.pt`.
# FIT="DIR ..." (folders of your look with ground truth, neither trained on nor TEST_DIR, e.g. 80
# stereo frames of other sequences) fits the end-identity coefficients for the new weights, so
# that the pose nodes still flag a frame whose tip they cannot tell (the folders are also read
# without colour, a look the new weights never saw), and their familiarity; without FIT the new
# weights state no end identity and every pose takes A as the tip.
set -euo pipefail
if [ $# -lt 3 ]; then sed -n 2,12p "$0"; exit 2; fi
OUT=$1; TEST=$2; shift 2
HERE=$(cd "$(dirname "$0")" && pwd)
INIT=${INIT:-$HERE/keypoint/model.pt}
CONFIG=${CONFIG:-$HERE/finetune.yaml}
NORMAL=${SUPPORT_NORMAL:-}   # e.g. SUPPORT_NORMAL=0,0,1 when the needle may rest on a surface of that normal
t0=$(date +%s)
data=(); for d in "$@"; do data+=(--data "$d"); done
needletrack train --init "$INIT" "${data[@]}" --config "$CONFIG" --out "$OUT"
echo "[$(( $(date +%s) - t0 )) s] fine-tuned: $OUT/model.pt"
rm -f "$OUT/end_identity.json" "$OUT/familiarity.json"   # fitted for earlier weights: they do not hold for these
if [ -n "${FIT:-}" ]; then
  fit=(); grey=(); for d in $FIT; do fit+=(--data "$d"); grey+=(--grey-data "$d"); done
  needletrack bench familiarity --weights "$OUT/model.pt" "${fit[@]}" --fit "$OUT/familiarity.json"
  echo "[$(( $(date +%s) - t0 )) s] familiarity fitted: $OUT/familiarity.json"
  needletrack bench end-identity --weights "$OUT/model.pt" "${fit[@]}" "${grey[@]}" --fit "$OUT/end_identity.json"
  echo "[$(( $(date +%s) - t0 )) s] end identity fitted: $OUT/end_identity.json"
else
  echo "warning: no FIT folders: $OUT/model.pt states no end identity (poses take A as the tip, never flagged for it)" >&2
fi
extra=(); [ -n "$NORMAL" ] && extra=(--support-normal "$NORMAL")
for w in before:"$INIT" after:"$OUT/model.pt"; do
  echo "== ${w%%:*}: ${w#*:}"
  [ -f "$OUT/eval_${w%%:*}/results.json" ] && continue   # scored by an earlier run
  needletrack eval --dataset "$TEST" --model "${w#*:}" --out "$OUT/eval_${w%%:*}" --quiet "${extra[@]}"
done
