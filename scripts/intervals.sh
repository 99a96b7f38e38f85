#!/usr/bin/env bash
# 3D-LAST at other scan intervals, one table per interval (docs/results.md, "Any scan interval"):
#   set up -> data (the interval-range training set, fresh test sets at 1 s, 5 s and U[4.5, 5.5] s, seed 99)
#   -> IMMNet over 0.5-5.5 s (recipes/interval-range.yaml: the shipped weights fine-tuned, about 13 minutes on 2 cores;
#   the whole script about 22)
#   -> every method that takes the data's interval, in one run per interval, beside the clairvoyant bound.
# A finished run is reused; IMMNET_RETRAIN=1 trains again.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
IMMNET="${IMMNET_VENV:-.venv}/bin/immnet"
export WANDB_MODE=${WANDB_MODE:-offline} WANDB_SILENT=true
RUN=runs/intervals
DATA=$RUN/data
gen() {  # name n seed config
  [ -f "$DATA/$1/meta.json" ] && { echo "  $DATA/$1 exists" >&2; return; }
  "$IMMNET" data generate --out "$DATA/$1" --n "$2" --seed "$3" ${4:+--config $4} --overwrite
}
gen train 3000 51 configs/data/intervals-0.5-5.5.yaml
gen test-1s 1000 99
gen test-5s 1000 99 configs/data/scan5.yaml
gen test-4.5-5.5s 1000 99 configs/data/scan4.5-5.5.yaml

CKPT=$RUN/stage2/checkpoints/best.ckpt
[ -n "${IMMNET_RETRAIN:-}" ] && rm -rf "$RUN/stage2"
if [ -f "$RUN/stage2/checkpoints/finished.json" ]; then
  echo "reusing the finished interval-range run $CKPT (IMMNET_RETRAIN=1 to train again)" >&2
else
  "$IMMNET" fit --config recipes/interval-range.yaml
fi

BASE=measurements,imm-min,imm-tuned,imm-ekf,imm-ekf-guard,imm-ekf-guard-sticky,clairvoyant-switch,clairvoyant
# the immnet row is the interval-range network; at 1 s the fixed-interval quick model is the main job's table
# (bash scripts/main.sh: the same test set, seed 99)
for set in test-1s test-5s test-4.5-5.5s; do
  "$IMMNET" evaluate --data "$DATA/$set" --split all --methods "$BASE,immnet" \
    --checkpoint "immnet=$CKPT" --json "$RUN/results-$set.json" --markdown "$RUN/results-$set.md"
done
echo "tables: $RUN/results-test-1s.md, $RUN/results-test-5s.md, $RUN/results-test-4.5-5.5s.md" >&2
