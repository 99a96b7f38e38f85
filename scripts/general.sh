#!/usr/bin/env bash
# The general IMMNet, from nothing to its tables (docs/immnet.md "The general model"), on a 2-core CPU in about 90 minutes (training
# about 40 of them):
#   set up -> data: 3D-LAST over U[0.5, 12] s scans (training) and test sets at 1 s, 5 s, U[4.5, 5.5] s and
#   U[0.5, 12] s (seed 99); real flights of collections/quickstart split by flight at 1 s and U[4.5, 5.5] s, every
#   other sample held out (bash scripts/real.sh's data) -> the general network (recipes/general.yaml: the 3D-LAST
#   weights widened to read the interval, fine-tuned on the mixture) -> one table per data set, every method that
#   takes the set's intervals in one run, beside the clairvoyant bound on 3D-LAST, the model-based filters
#   tuned on the training flights on real flights, and on every set imm-ekf-general, IMMNet with nothing learned
#   tuned on the network's own training mixture (configs/methods/imm-ekf-general.yaml; IMMNET_RETUNE=1 tunes it
#   again, about 7 minutes).
# A finished run is reused; IMMNET_RETRAIN=1 trains again. IMMNET_SKIP_HELDOUT=1 leaves out the held-out samples
# (2,600 + 1,700 windows: about 30 of the 90 minutes).
set -euo pipefail
cd "$(dirname "$0")/.."
T0=$(date +%s)
bash scripts/setup.sh
VENV=${IMMNET_VENV:-.venv}
IMMNET="$VENV/bin/immnet"
export WANDB_MODE=${WANDB_MODE:-offline} WANDB_SILENT=true
RUN=runs/general
DATA=$RUN/data
REAL=runs/real/data
say() { local e=$(( $(date +%s) - T0 )); printf '\n[general %dm%02ds] %s\n' $((e / 60)) $((e % 60)) "$*" >&2; }

say "1/3 data"
gen() {  # name n seed [config]
  [ -f "$DATA/$1/meta.json" ] && { echo "  $DATA/$1 exists" >&2; return; }
  "$IMMNET" data generate --out "$DATA/$1" --n "$2" --seed "$3" ${4:+--config $4} --overwrite
}
gen 3dlast 1500 61 configs/data/intervals-0.5-12.yaml
gen 3dlast-1s 500 63
gen test-1s 1000 99
gen test-5s 1000 99 configs/data/scan5.yaml
gen test-4.5-5.5s 1000 99 configs/data/scan4.5-5.5.yaml
gen test-0.5-12s 1000 99 configs/data/scan0.5-12.yaml
gen test-10-12s 1000 99 configs/data/scan10-12.yaml
HELDOUT=$("$VENV/bin/python" -c "from immnet.data.adsb import available_samples as a; print(' '.join(n for n in a() if n != 'collections/quickstart'))")
adsb() {  # name splits samples... (as scripts/real.sh)
  local name=$1 splits=$2; shift 2
  [ -f "$REAL/$name/test/meta.json" ] && { echo "  $REAL/$name exists" >&2; return; }
  "$IMMNET" data adsb --out "$REAL/$name" --splits "$splits" --seed 0 --overwrite --quiet "$@"
}
SCAN5=(--dt 5 --dt-jitter 0.5 --T 60 --r 5,35)
adsb quickstart-1s 0.7,0.15,0.15 --samples collections/quickstart
adsb quickstart-5s 0.7,0.15,0.15 --samples collections/quickstart "${SCAN5[@]}"
if [ -z "${IMMNET_SKIP_HELDOUT:-}" ]; then
  # shellcheck disable=SC2086
  adsb heldout-1s all-test --skip-unreadable --samples $HELDOUT
  # shellcheck disable=SC2086
  adsb heldout-5s all-test --skip-unreadable --samples $HELDOUT "${SCAN5[@]}"
fi

if [ -n "${IMMNET_RETUNE:-}" ]; then
  say "tuning imm-ekf-general on the network's training mixture"
  "$IMMNET" tune --search configs/tuning/imm-ekf-general.yaml --data "$DATA/3dlast" "$REAL/quickstart-1s/train" \
    "$REAL/quickstart-5s/train" --out configs/methods/imm-ekf-general.yaml --quiet
fi

CKPT=$RUN/fit/checkpoints/best.ckpt
[ -n "${IMMNET_RETRAIN:-}" ] && rm -rf "$RUN/fit"
if [ -f "$RUN/fit/checkpoints/finished.json" ]; then
  say "2/3 the general network: reusing the finished run $CKPT (IMMNET_RETRAIN=1 to train again)"
else
  say "2/3 the general network: recipes/general.yaml"
  "$IMMNET" fit --config recipes/general.yaml
fi

say "3/3 tables: one per data set, every method in one run"
table() {  # data name methods
  "$IMMNET" evaluate --data "$1" --split all --methods "$3" --checkpoint "immnet-general=$CKPT" \
    --json "$RUN/results-$2.json" --markdown "$RUN/results-$2.md" --quiet
}
LAST=measurements,imm-tuned,imm-ekf,imm-ekf-guard-sticky,imm-ekf-general,clairvoyant-switch,clairvoyant
table "$DATA/test-1s" 3dlast-1s "$LAST,immnet,immnet-general"  # immnet: the 3D-LAST network (1 s only)
for set in 5s 4.5-5.5s 0.5-12s; do
  table "$DATA/test-$set" "3dlast-$set" "$LAST,immnet-general"
done
REAL1=measurements,imm-ekf,imm-ekf-general,real-ca,real-imm,real-imm-axis,real-imm-channel,real-imm-singer
REAL5=measurements,imm-ekf,imm-ekf-general,real-ca-5s,real-imm-5s,real-imm-axis-5s,real-imm-channel-5s,real-imm-singer-5s
sets=(quickstart)
[ -z "${IMMNET_SKIP_HELDOUT:-}" ] && sets+=(heldout)
for s in "${sets[@]}"; do
  # on real flights no range guard (3D-LAST's region is not theirs), for every method
  "$IMMNET" evaluate --data "$REAL/$s-1s/test" --split all --guard none --methods "$REAL1,immnet,immnet-real,immnet-general" \
    --checkpoint "immnet-general=$CKPT" --json "$RUN/results-$s-1s.json" --markdown "$RUN/results-$s-1s.md" --quiet
  "$IMMNET" evaluate --data "$REAL/$s-5s/test" --split all --guard none --methods "$REAL5,immnet-general" \
    --checkpoint "immnet-general=$CKPT" --json "$RUN/results-$s-5s.json" --markdown "$RUN/results-$s-5s.md" --quiet
done
say "done. Tables: $RUN/results-*.md"
