#!/usr/bin/env bash
# Set up (if needed) and run the whole test suite, slow end-to-end tests included.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
VENV=${IMMNET_VENV:-.venv}
export WANDB_MODE=offline WANDB_SILENT=true
# two workers on the two cores, each test file on one worker (its module fixtures run once); each
# worker's torch on one thread, so the two do not oversubscribe the cores
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
"$VENV/bin/python" -m pytest -q -n "${IMMNET_TEST_WORKERS:-2}" --dist loadfile "$@"
