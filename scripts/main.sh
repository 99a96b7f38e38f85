#!/usr/bin/env bash
# The main job, from nothing to the results table, on an idle 2-core CPU in about 15 minutes (budgets are steps,
# not time: a busy machine takes longer, never cuts the training short, and prints progress each minute):
#   set up -> generate 3D-LAST data -> train IMMNet (recipes/quick.yaml) -> evaluate every method on a
#   held-out test set in one run -> table + figures.
# A finished quick run is reused, an interrupted one resumes; IMMNET_RETRAIN=1 retrains from scratch.
set -euo pipefail
cd "$(dirname "$0")/.."
T0=$(date +%s)  # the elapsed time in each progress line counts from here, set-up included
bash scripts/setup.sh
VENV=${IMMNET_VENV:-.venv}
IMMNET="$VENV/bin/immnet"
export WANDB_MODE=${WANDB_MODE:-offline} WANDB_SILENT=true
# every W&B run of this job (training stages, plain KalmanNet, evaluation) in one group (docs/wandb.md)
export WANDB_RUN_GROUP=${WANDB_RUN_GROUP:-main}
SINCE=$(mktemp)  # the W&B runs written after this file are this job's
trap 'rm -f "$SINCE"' EXIT
RUN=runs/quick
DATA=$RUN/data
say() { local e=$(( $(date +%s) - T0 )); printf '\n[main %dm%02ds] %s\n' $((e / 60)) $((e % 60)) "$*" >&2; }

say "1/4 data: 3D-LAST train 3000 + 4 x 600 single-mode (stage 1) + a fresh test set of 1000 (seed 99)"
gen() {  # name n seed [mode]
  [ -f "$DATA/$1/meta.json" ] && { echo "  $DATA/$1 exists" >&2; return; }
  "$IMMNET" data generate --out "$DATA/$1" --n "$2" --seed "$3" ${4:+--single-mode $4} --overwrite
}
gen train 3000 11
gen single-cv 600 12 cv
gen single-ca 600 13 ca
gen single-ct+ 600 14 ct+
gen single-ct- 600 15 ct-
gen test 1000 99

fit() {  # immnet fit; a run stopped short of its step budget (exit 3, docs/immnet.md) ends the job, said plainly
  local rc=0
  "$IMMNET" fit "$@" || rc=$?
  if [ "$rc" = 3 ]; then
    say "stopped: a training run ended short of its step budget (above), so it is not the recipe's model and no table is made from it; rerun bash scripts/main.sh to resume it"
  fi
  [ "$rc" = 0 ] || exit "$rc"
}
CKPT=$RUN/stage2/checkpoints/best.ckpt
# a run that ended has finished.json beside its checkpoints; an interrupted one resumes (the chain skips a
# finished stage and resumes the other from its last.ckpt: docs/immnet.md, "What a run saves")
if [ -n "${IMMNET_RETRAIN:-}" ]; then
  rm -rf "$RUN/stage1" "$RUN/stage2" runs/ablations/single-expert
fi
if [ -f "$RUN/stage2/checkpoints/finished.json" ]; then
  say "2/4 training: reusing the finished quick run $CKPT (IMMNET_RETRAIN=1 to train again)"
else
  say "2/4 training: recipes/quick.yaml (on 2 idle cores stage 1 about 3.5 min, stage 2 about 5 min; a busy machine is slower, each minute's progress line says how long is left; an interrupted run resumes)"
  WANDB_JOB_TYPE=train fit --config recipes/quick.yaml  # runs "quick 1/2", "quick 2/2"
fi
# the table's plain KalmanNet: one KalmanNet (architecture 2, CA) alone on maneuvering data, at the
# quick stage-1 budget (the single-expert ablation; scripts/ablations.py reuses it)
KDIR=runs/ablations/single-expert/checkpoints
KNET=$KDIR/best.ckpt
if [ -f "$KDIR/finished.json" ]; then
  say "2/4 training: reusing the plain KalmanNet $KNET"
elif [ -f "$KDIR/last.ckpt" ]; then
  say "2/4 training: plain KalmanNet, resuming $KDIR/last.ckpt"
  WANDB_JOB_TYPE=train WANDB_NAME=kalmannet fit --config configs/ablations/single-expert.yaml --ckpt_path last
else
  say "2/4 training: plain KalmanNet (configs/ablations/single-expert.yaml, about 1 min)"
  WANDB_JOB_TYPE=train WANDB_NAME=kalmannet fit --config configs/ablations/single-expert.yaml --overwrite_checkpoints true
fi

say "3/4 evaluation: every method on the test set, one run"
"$IMMNET" evaluate --data "$DATA/test" --split all \
  --methods measurements,imm-accurate,imm-min,imm-max,imm-tuned,imm-ekf,imm-ekf-guard,imm-ekf-guard-sticky,kalmannet,immnet,clairvoyant-switch,clairvoyant \
  --checkpoint "immnet=$CKPT" --checkpoint "kalmannet=$KNET" \
  --json "$RUN/results.json" --markdown "$RUN/results.md" --figures "$RUN/figures" \
  --wandb --wandb-name evaluate --wandb-dir runs

say "4/4 figures: dataset overview"
"$IMMNET" data plot --data "$DATA/train" --out "$RUN/figures/dataset.png" --n 400

say "done. Artifacts:
  results table  $RUN/results.md   (JSON: $RUN/results.json)
  figures        $RUN/figures/  (dataset overview, RMSE over time, case-study tracks, mode probabilities, confusion)
  checkpoints    $RUN/stage1/checkpoints/best.ckpt, $CKPT, $KNET (plain KalmanNet)"
OFFLINE=$(find runs/wandb -maxdepth 1 -name 'offline-run-*' -newer "$SINCE" 2>/dev/null | sort || true)
if [ -n "$OFFLINE" ]; then
  printf '\nW&B: the offline runs of this job (group %s):\n%s\nupload them (needs network and `wandb login`):\n  %s/bin/wandb sync %s\n' \
    "$WANDB_RUN_GROUP" "$(sed 's/^/  /' <<< "$OFFLINE")" "$VENV" "$(tr '\n' ' ' <<< "$OFFLINE")" >&2
else
  echo "W&B: no offline run written (WANDB_MODE=$WANDB_MODE)" >&2
fi
