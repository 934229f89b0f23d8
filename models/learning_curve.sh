#!/usr/bin/env bash
# The hand-label learning curve (issue 55; docs/adapt.md, "The learning curve"): on a look no
# training render uses, label 10, 30 and 100 stereo frames of a train split by simulated clicks
# (the truth with 2 px of noise, through the page's own fit and save: `needletrack bench label`),
# fine-tune the shipped detector on each (`needletrack finetune`), and score every weights on the
# look's test set (`needletrack eval`), beside the shipped weights and a fine-tune on all 400
# frames of the split with their full truth (models/finetune.sh).
#   bash models/learning_curve.sh LOOK WORK      LOOK: alt_threadless | silicone
# WORK/test is the look's set of docs/results.md; WORK/train (400 frames, 200 takes of 2 endoscope
# poses) and WORK/dev (40, the full-truth fine-tune's fits) are other seeds of the same look.
# THREADS=1 runs the trainings on one thread (two looks side by side on a 2-core machine).
# Resumable: rerun the same command; each step whose output exists is skipped. Prints the
# wall-clock of each step; `python -m common.adapt.learning_curve WORK ...` tabulates and plots.
set -euo pipefail
if [ $# -ne 2 ]; then sed -n 2,14p "$0"; exit 2; fi
LOOK=$1; W=$2
HERE=$(cd "$(dirname "$0")" && pwd)
THREADS=${THREADS:-}
SIZES=${SIZES:-"30 10 100"}
t0=$(date +%s)
stamp() { echo "[$(( $(date +%s) - t0 )) s] $LOOK: $*"; }
mkdir -p "$W"
case "$LOOK" in
  alt_threadless)
    make() { needletrack dataset generate-alt --out "$1" --sequences "$2" --steps "$3" --seed "$4" --thread none --quiet; } ;;
  silicone)
    make() { needletrack dataset generate --out "$1" --sequences "$2" --steps "$3" --seed "$4" --randomise silicone --thread none --quiet; } ;;
  *) echo "LOOK must be alt_threadless or silicone, got $LOOK" >&2; exit 2 ;;
esac
evaluate() {  # weights, out
  [ -f "$2/results.json" ] || needletrack eval --dataset "$W/test" --detector learned --model "$1" \
      --support-normal 0,0,1 --out "$2" --quiet > "$2.log" 2>&1
}
# the sets: test as in docs/results/sets.yaml; train and dev of other seeds
[ -f "$W/test/.done" ] || { case "$LOOK" in alt_threadless) make "$W/test" 30 5 2000 ;; silicone) make "$W/test" 30 5 4000 ;; esac; touch "$W/test/.done"; }
[ -f "$W/train/.done" ] || { make "$W/train" 200 2 5501; touch "$W/train/.done"; }
[ -f "$W/dev/.done" ] || { make "$W/dev" 20 2 5502; touch "$W/dev/.done"; }
stamp "sets rendered"
fcfg=()
if [ -n "$THREADS" ]; then fcfg=(--threads "$THREADS"); sed "s/^  threads: .*/  threads: $THREADS/" "$HERE/finetune.yaml" > "$W/finetune_ref.yaml"; fi
evaluate "$HERE/keypoint/model.pt" "$W/eval_shipped"
stamp "shipped weights scored"
for n in $SIZES; do
  if [ ! -f "$W/labels_$n.json" ]; then
    rm -rf "$W/labels_$n"
    needletrack bench label --dataset "$W/train" --end-px 2 --wire-px 2 --max-frames "$n" --out "$W/labels_$n" \
        --json "$W/labels_$n.tmp.json" --quiet > "$W/labels_$n.log" 2>&1
    mv "$W/labels_$n.tmp.json" "$W/labels_$n.json"
  fi
  s=$(date +%s)
  [ -f "$W/ft_$n/finetune.json" ] || needletrack finetune --labels "$W/labels_$n" --out "$W/ft_$n" --quiet "${fcfg[@]}" > "$W/ft_$n.log" 2>&1
  echo "$(( $(date +%s) - s ))" > "$W/ft_$n.seconds"
  stamp "$n labelled frames fine-tuned ($(cat "$W/ft_$n.seconds") s)"
  evaluate "$W/ft_$n/model.pt" "$W/eval_$n"
  stamp "$n labelled frames scored"
  if [ "$n" = "$(echo $SIZES | cut -d' ' -f1)" ] && [ ! -f "$W/ref/eval_after/results.json" ]; then
    # the reference: all 400 frames of the split with their full truth, its fits on dev
    [ -n "$THREADS" ] && export CONFIG="$W/finetune_ref.yaml"
    mkdir -p "$W/ref"; [ -e "$W/ref/eval_before" ] || ln -s ../eval_shipped "$W/ref/eval_before"
    s=$(date +%s)
    SUPPORT_NORMAL=0,0,1 FIT="$W/dev" bash "$HERE/finetune.sh" "$W/ref" "$W/test" "$W/train" > "$W/ref.log" 2>&1 || true
    echo "$(( $(date +%s) - s ))" > "$W/ref.seconds"
    stamp "full-truth fine-tune on 400 frames done ($(cat "$W/ref.seconds") s, its scores in $W/ref/eval_after)"
  fi
done
stamp "done"
