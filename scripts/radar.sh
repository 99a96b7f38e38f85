#!/usr/bin/env bash
# A radar's plots of real flights, from nothing to the tables (docs/radar.md), on a 2-core CPU in about 30 minutes:
#   data: collections/quickstart split by flight (the partition every real-flight network was trained on: --seed 0) and
#   every other sample held out (its flights known every second), each flight seen by a radar 10-100 km away
#   (40 m / 0.12 deg / 0.2 deg, 5 % missed) at 4.5-5.5 s and 10-12 s scans, clean and with 2 % outliers at 10x
#   -> the model-based IMMs told each plot's covariance, plain and robust, tuned on the training flights (clean and
#   outliers together; IMMNET_RETUNE=1 tunes them again) -> one table per set, every method in one run, and the
#   knock-outs of the band's shipped network, the worst track and the 95 % ellipsoid coverage (scripts/radar_report.py).
set -euo pipefail
cd "$(dirname "$0")/.."
T0=$(date +%s)
VENV=${IMMNET_VENV:-.venv}
PY="$VENV/bin/python"
IMMNET="$PY -m immnet.cli"
export WANDB_MODE=${WANDB_MODE:-offline} WANDB_SILENT=true OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
RUN=runs/radar
DATA=$RUN/data
say() { local e=$(( $(date +%s) - T0 )); printf '\n[radar %dm%02ds] %s\n' $((e / 60)) $((e % 60)) "$*" >&2; }

RADAR=(--sigma-range 40,40 --sigma-azimuth 0.12,0.12 --sigma-elevation 0.2,0.2 --range-km 10,100 --p-miss 0.05)
OUTLIERS=(--outliers 0.02 --outlier-scale 10)
S5=(--dt 5 --dt-jitter 0.5 --T 60)
S11=(--dt 11 --dt-jitter 1 --T 30)
HELDOUT=$("$PY" -c "from immnet.data.adsb import available_samples as a; print(' '.join(n for n in a() if n != 'collections/quickstart'))")
say "1/3 data"
for s in 5 11; do
  eval "S=(\"\${S$s[@]}\")"
  [ -f "$DATA/q$s-clean/test/meta.json" ] || $IMMNET data adsb --out "$DATA/q$s-clean" --splits 0.7,0.15,0.15 --seed 0 --overwrite --quiet --samples collections/quickstart "${S[@]}" "${RADAR[@]}"
  [ -f "$DATA/q$s-out/test/meta.json" ] || $IMMNET data adsb --out "$DATA/q$s-out" --splits 0.7,0.15,0.15 --seed 0 --overwrite --quiet --samples collections/quickstart "${S[@]}" "${RADAR[@]}" "${OUTLIERS[@]}"
  [ -f "$DATA/h$s-clean/test/meta.json" ] || $IMMNET data adsb --out "$DATA/h$s-clean" --splits all-test --seed 0 --overwrite --quiet --skip-unreadable --samples $HELDOUT "${S[@]}" "${RADAR[@]}" --max-position-interval 2
  [ -f "$DATA/h$s-out/test/meta.json" ] || $IMMNET data adsb --out "$DATA/h$s-out" --splits all-test --seed 0 --overwrite --quiet --skip-unreadable --samples $HELDOUT "${S[@]}" "${RADAR[@]}" "${OUTLIERS[@]}" --max-position-interval 2
done
say "2/3 the model-based IMMs told each plot's covariance, tuned on the training flights"
if [ "${IMMNET_RETUNE:-0}" = 1 ]; then
  for s in 5 11; do
    for n in radar-imm radar-imm-robust; do
      $IMMNET tune --quiet --search "configs/tuning/$n-${s}s.yaml" --data "$DATA/q$s-clean/train" "$DATA/q$s-out/train" --out "configs/methods/$n-${s}s.yaml"
    done
  done
fi
say "3/3 tables"
for s in 5 11; do
  for set in q$s-clean q$s-out h$s-clean h$s-out; do
    $IMMNET evaluate --data "$DATA/$set/test" --split all --guard none --quiet \
      --methods "measurements,real-imm-singer-${s}s,radar-imm-${s}s,radar-imm-robust-${s}s,immnet-real-${s}s,immnet-bank" \
      --json "$RUN/$set.json" --markdown "$RUN/$set.md"
    $PY scripts/learned_parts.py --data "$DATA/$set/test" --checkpoint immnet/pretrained/immnet-real-${s}s.ckpt \
      --label immnet-real-${s}s --baselines radar-imm-${s}s --json "$RUN/$set-parts.json" --markdown "$RUN/$set-parts.md"
    $PY scripts/radar_report.py --data "$DATA/$set/test" --split all --methods "measurements,radar-imm-${s}s,radar-imm-robust-${s}s,immnet-real-${s}s,immnet-bank" \
      --json "$RUN/$set-report.json" --markdown "$RUN/$set-report.md"
  done
done
say "done: $RUN/*.md"
