#!/usr/bin/env bash
# Set up IMMNet in a virtual environment (.venv by default; IMMNET_VENV to change).
# Installs PyTorch first where none is present: the CPU build 2.13.0 (on our machines it lies on disk;
# set IMMNET_TORCH to another requirement, e.g. a CUDA build, or preinstall your own torch).
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${IMMNET_VENV:-.venv}
if [ ! -x "$VENV/bin/python" ]; then
  echo "[setup] creating virtual environment $VENV"
  python3 -m venv "$VENV"
fi
PY="$VENV/bin/python"
if ! "$PY" -c "import torch" 2>/dev/null; then
  echo "[setup] installing ${IMMNET_TORCH:-torch==2.13.0}"
  "$PY" -m pip install -q "${IMMNET_TORCH:-torch==2.13.0}" 2> >(grep -v "is ignored: it is neither" >&2)
fi
if ! "$PY" -c "import immnet, filterpy, pytest, xdist, stonesoup" 2>/dev/null; then
  echo "[setup] installing immnet with its dev extra"
  "$PY" -m pip install -q -e ".[dev]" 2> >(grep -v "is ignored: it is neither" >&2)
fi
# the ADS-B sample files of `immnet data adsb` and its tests: traffic's wheel without its dependencies
# (immnet reads its JSON files and never imports it; docs/real-data.md, "Real flights")
if ! "$PY" -c "import importlib.util, sys; sys.exit(importlib.util.find_spec('traffic') is None)"; then
  echo "[setup] installing the ADS-B sample files (traffic==2.13, --no-deps)"
  "$PY" -m pip install -q --no-deps "traffic==2.13" 2> >(grep -v "is ignored: it is neither" >&2) \
    || echo "[setup] traffic's sample files could not be installed: the quickstart test is skipped" >&2
fi
echo "[setup] ready: $("$PY" -c 'import torch, immnet; print("torch", torch.__version__)')"
