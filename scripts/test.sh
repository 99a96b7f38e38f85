#!/usr/bin/env bash
# Set up (if needed) and run the whole test suite, slow end-to-end tests included.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
VENV=${IMMNET_VENV:-.venv}
export WANDB_MODE=offline WANDB_SILENT=true
"$VENV/bin/python" -m pytest -q "$@"
