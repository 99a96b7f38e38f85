#!/usr/bin/env bash
# Real flights, from nothing to the tables (docs/real.md), on a 2-core CPU in about 70 minutes (the sum of its steps:
# data 3, training 55 (three runs side by side on the two cores, each 80 steps in about 107 s), the evaluation 10, the
# rest 3):
#   set up (with traffic's sample files) -> data: collections/quickstart split by flight at 1 s, U[4.5, 5.5] s, U[6, 8] s
#   and U[10, 12] s scans, every other sample held out (never trained or tuned on; all its flights, and apart those known every
#   second) -> the model-based filters for real motion as tuned on the training flights (configs/methods/real-*.yaml;
#   IMMNET_RETUNE=1 tunes them again) -> IMMNet
#   trained on the training flights (recipes/real-singer-output.yaml three times, two with an overlay of
#   configs/members/: output corrections on the three-filter decoupled IMM, r estimated, joined into one network, the
#   shipped immnet-real) -> one table per data set, every method in one run -> the real-flight figure.
# A finished run is reused; IMMNET_RETRAIN=1 trains again.
set -euo pipefail
cd "$(dirname "$0")/.."
T0=$(date +%s)
bash scripts/setup.sh
VENV=${IMMNET_VENV:-.venv}
PY="$VENV/bin/python"
IMMNET="$VENV/bin/immnet"
export WANDB_MODE=${WANDB_MODE:-offline} WANDB_SILENT=true
RUN=runs/real
DATA=$RUN/data
say() { local e=$(( $(date +%s) - T0 )); printf '\n[real %dm%02ds] %s\n' $((e / 60)) $((e % 60)) "$*" >&2; }

say "1/5 data: quickstart (train/val/test by flight) and every other sample (held out), at 1 s and 4.5-5.5 s"
HELDOUT=$("$PY" -c "from immnet.data.adsb import available_samples as a; print(' '.join(n for n in a() if n != 'collections/quickstart'))")
adsb() {  # name splits samples... -- options
  local name=$1 splits=$2; shift 2
  [ -f "$DATA/$name/meta.json" ] || [ -f "$DATA/$name/test/meta.json" ] && { echo "  $DATA/$name exists" >&2; return; }
  "$IMMNET" data adsb --out "$DATA/$name" --splits "$splits" --seed 0 --overwrite --quiet "$@"
}
SCAN5=(--dt 5 --dt-jitter 0.5 --T 60 --r 5,35)  # a surveillance radar: 4.5-5.5 s scans, 5-35 m noise, 300 s windows
SCAN7=(--dt 7 --dt-jitter 1 --T 40 --r 5,35)  # between the two: 6-8 s scans, the same noise, 280 s windows
SCAN11=(--dt 11 --dt-jitter 1 --T 30 --r 5,35)  # an en-route radar: 10-12 s scans, the same noise, 330 s windows
adsb quickstart-1s 0.7,0.15,0.15 --samples collections/quickstart
adsb quickstart-5s 0.7,0.15,0.15 --samples collections/quickstart "${SCAN5[@]}"
adsb quickstart-7s 0.7,0.15,0.15 --samples collections/quickstart "${SCAN7[@]}"
adsb quickstart-11s 0.7,0.15,0.15 --samples collections/quickstart "${SCAN11[@]}"
# shellcheck disable=SC2086
adsb heldout-1s all-test --skip-unreadable --samples $HELDOUT
# shellcheck disable=SC2086
adsb heldout-5s all-test --skip-unreadable --samples $HELDOUT "${SCAN5[@]}"
# shellcheck disable=SC2086
adsb heldout-7s all-test --skip-unreadable --samples $HELDOUT "${SCAN7[@]}"
# shellcheck disable=SC2086
adsb heldout-11s all-test --skip-unreadable --samples $HELDOUT "${SCAN11[@]}"
# the held-out flights known every second (85 % of the held-out windows are of flights known every 5 s, whose truth
# between positions is the smoother's interpolation): the same windows as theirs in the sets above
DENSE=(--max-position-interval 2)
# shellcheck disable=SC2086
adsb heldout-1s-dense all-test --skip-unreadable --samples $HELDOUT "${DENSE[@]}"
# shellcheck disable=SC2086
adsb heldout-5s-dense all-test --skip-unreadable --samples $HELDOUT "${SCAN5[@]}" "${DENSE[@]}"
# shellcheck disable=SC2086
adsb heldout-11s-dense all-test --skip-unreadable --samples $HELDOUT "${SCAN11[@]}" "${DENSE[@]}"
if [ -n "${IMMNET_RETUNE:-}" ]; then
  say "2/5 tuning the model-based filters on the training flights (at 1, 4.5-5.5, 6-8 and 10-12 s)"
  for m in real-ca real-imm-axis real-imm real-imm-channel real-imm-singer; do
    for tag in "" -5s -7s -11s; do  # the configs' suffix; the 1 s set is quickstart-1s
      "$IMMNET" tune --search "configs/tuning/$m.yaml" --data "$DATA/quickstart${tag:--1s}/train" \
        --out "configs/methods/$m$tag.yaml" --quiet
    done
  done
else
  say "2/5 the model-based filters as tuned on the training flights: configs/methods/real-*.yaml (IMMNET_RETUNE=1 to tune again)"
fi

# the shipped real averages three runs' corrections on one filter (docs/notebook/real-flights.md "Several corrections on
# one filter"): the recipe, and the recipe with each overlay of configs/members/ (another seed; turns flown into its views)
MEMBERS=(output:- output-seed1:configs/members/real-seed1.yaml output-turns:configs/members/real-turns.yaml)
member() {  # run-directory:overlay (- for none)
  local dir=${1%%:*} overlay=${1#*:} extra=()
  [ "$overlay" = - ] || extra=(--config "$overlay")
  if [ -f "$RUN/$dir/checkpoints/best.ckpt" ] && [ -f "$RUN/$dir/checkpoints/finished.json" ]; then
    echo "  reusing the finished training $RUN/$dir (IMMNET_RETRAIN=1 to train again)" >&2
    return
  fi
  OMP_NUM_THREADS=1 "$IMMNET" fit --config recipes/real-singer-output.yaml "${extra[@]}" 2>&1 | sed -u "s|^|[$dir] |" >&2
}
if [ -n "${IMMNET_RETRAIN:-}" ]; then for m in "${MEMBERS[@]}"; do rm -rf "${RUN:?}/${m%%:*}"; done; fi
say "3/5 IMMNet trained on the training flights: recipes/real-singer-output.yaml three times, side by side (about 55 min)"
# each member in a process group of its own, so that a stopped, interrupted or failed script stops every member whole
set -m
pids=()
trap 'for p in "${pids[@]}"; do kill -- "-$p" 2>/dev/null || true; done' EXIT
trap 'exit 130' INT
trap 'exit 143' TERM
for m in "${MEMBERS[@]}"; do member "$m" & pids+=($!); done
for p in "${pids[@]}"; do wait "$p"; done
pids=()
set +m
trap - INT TERM
CKPT=$RUN/joined/immnet-real.ckpt  # their corrections joined: the network make_shipped.py --name real exports
ckpts=()
for m in "${MEMBERS[@]}"; do ckpts+=("$RUN/${m%%:*}/checkpoints/best.ckpt"); done
"$PY" -m immnet.training.export --join "${ckpts[@]}" "$CKPT" >/dev/null

say "4/5 evaluation: one table per data set, every method in one run"
# immnet-bank is the default as shipped: its members are the shipped files (its real network is not this run's)
BASE=measurements,imm-tuned,imm-ekf,imm-ekf-general,real-ca,real-imm,real-imm-axis,real-imm-channel,real-imm-singer
tuned() { echo "real-ca$1,real-imm$1,real-imm-axis$1,real-imm-channel$1,real-imm-singer$1"; }  # the five tuned at a set's scans
score() {  # "METHODS" SET...: one table per set, every method in one run; more evaluate options in the array OPTS
  local methods=$1 set; shift
  for set in "$@"; do
    "$IMMNET" evaluate --data "$DATA/$set/test" --split all --guard none --methods "$methods" "${OPTS[@]}" \
      --json "$RUN/results-$set.json" --markdown "$RUN/results-$set.md" --quiet
  done
}
OPTS=(--checkpoint "immnet-real=$CKPT")
score "$BASE,immnet,immnet-real,immnet-general,immnet-bank" quickstart-1s heldout-1s heldout-1s-dense
OPTS=()
# the 1 s networks refuse longer scans; general, the bank and the real-flight networks trained for them take them
score "$BASE,$(tuned -5s),immnet-general,immnet-real-5s,immnet-bank" quickstart-5s heldout-5s heldout-5s-dense
score "$BASE,real-imm-singer-5s,real-imm-singer-11s,$(tuned -7s),immnet-general,immnet-real-4.5-12s,immnet-bank" \
  quickstart-7s heldout-7s
score "$BASE,real-imm-singer-5s,$(tuned -11s),immnet-general,immnet-real-11s,immnet-bank" \
  quickstart-11s heldout-11s heldout-11s-dense

say "5/5 figure: a real flight, its estimates and their error over time"
"$PY" scripts/real_figure.py --data "$DATA/quickstart-1s/test" --methods real-imm-singer,immnet-real \
  --checkpoint "immnet-real=$CKPT" --out "$RUN/figures/real_flight.png"

say "done. Tables: $RUN/results-{quickstart-1s,heldout-1s,heldout-1s-dense,quickstart-5s,heldout-5s,heldout-5s-dense,quickstart-7s,heldout-7s,quickstart-11s,heldout-11s,heldout-11s-dense}.md"
