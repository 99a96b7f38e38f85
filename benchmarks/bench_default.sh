#!/bin/bash
# The default tracker against a filter, whole processes (BENCHMARKS.md "The default tracker against a filter"):
# `immnet track` with no options (the bank) and `immnet track --method real-imm-singer --r 4` on the same CSV, in turn
# (A B A B ...) after one warm-up each, each run under /usr/bin/time; prints each one's median wall and CPU (user + sys)
# seconds and the median of the runs' ratios A/B, pair by pair (a ratio holds where a shared machine's speed drifts).
# Run from a checkout: benchmarks/bench_default.sh CSV [RUNS (5)] [PYTHON (.venv/bin/python)]; the package measured is
# the checkout's (PYTHONPATH), one thread (OMP_NUM_THREADS=1). The CSV: benchmarks/track_csv.py.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
csv=$(realpath "$1")
runs=${2:-5}
python=${3:-$root/.venv/bin/python}
export PYTHONPATH=$root OMP_NUM_THREADS=1 WANDB_MODE=offline WANDB_SILENT=true
cd "$root"  # python -m puts the working directory first on sys.path
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
echo "$(git -C "$root" rev-parse --short HEAD); $(nproc --all) CPUs; load average $(cut -d' ' -f1-3 /proc/loadavg); $csv"
one() {  # one(LOG, ARGS...): one run of immnet track, its user, sys and wall seconds appended to LOG
  local log=$1; shift
  rm -f "$work/out.csv"
  /usr/bin/time -o "$log" -a -f "%U %S %e" "$python" -m immnet.cli track --input "$csv" --output "$work/out.csv" "$@" \
    2>/dev/null
}
one "$work/warm" && one "$work/warm" --method real-imm-singer --r 4
for _ in $(seq "$runs"); do
  one "$work/a"
  one "$work/b" --method real-imm-singer --r 4
done
"$python" - "$work/a" "$work/b" <<'PY'
import statistics, sys
a, b = ([list(map(float, line.split())) for line in open(path) if line.strip()] for path in sys.argv[1:3])
for name, rows in (("immnet track (the default)", a), ("immnet track --method real-imm-singer --r 4", b)):
    print(f"{name:<44} median wall {statistics.median(r[2] for r in rows):6.2f} s, "
          f"median CPU {statistics.median(r[0] + r[1] for r in rows):6.2f} s")
wall = [x[2] / y[2] for x, y in zip(a, b)]
cpu = [(x[0] + x[1]) / (y[0] + y[1]) for x, y in zip(a, b)]
print(f"ratio default / filter, median of {len(wall)} pairs: wall {statistics.median(wall):.2f}x "
      f"({min(wall):.2f}-{max(wall):.2f}), CPU {statistics.median(cpu):.2f}x ({min(cpu):.2f}-{max(cpu):.2f})")
PY
