#!/bin/bash
# The default tracker against a filter, whole processes (BENCHMARKS.md "The default tracker against a filter"):
# `immnet track` with no options (the bank) and `immnet track --method real-imm-singer --r 4` on the same CSV, in turn
# (A B A B ...) after one warm-up each, each run under /usr/bin/time; prints each one's median wall and CPU (user + sys)
# seconds and the median of the runs' ratios A/B, pair by pair (a ratio holds where a shared machine's speed drifts).
# Run from a checkout: benchmarks/bench_default.sh CSV [RUNS (5)] [PYTHON (.venv/bin/python)] [BEFORE]; the package
# measured is the checkout's (PYTHONPATH), one thread (OMP_NUM_THREADS=1). BEFORE, another checkout (e.g. `git
# worktree add /tmp/before REV`): its `immnet track` runs in turn with the two (A0 A B A0 A B ...), and its ratios to
# B and A's to it are printed too. The CSV: benchmarks/track_csv.py.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
csv=$(realpath "$1")
runs=${2:-5}
python=${3:-$root/.venv/bin/python}
case $python in */*) python=$(cd "$(dirname "$python")" && pwd)/$(basename "$python") ;; esac  # BEFORE runs it too
before=${4:+$(cd "$4" && pwd)}
export PYTHONPATH=$root OMP_NUM_THREADS=1 WANDB_MODE=offline WANDB_SILENT=true
cd "$root"  # python -m puts the working directory first on sys.path
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
echo "$(git -C "$root" rev-parse --short HEAD)${before:+ (before: $(git -C "$before" rev-parse --short HEAD))}; \
$(nproc --all) CPUs; load average $(cut -d' ' -f1-3 /proc/loadavg); $csv"
one() {  # one(LOG, ARGS...): one run of immnet track, its user, sys and wall seconds appended to LOG
  local log=$1; shift
  rm -f "$work/out.csv"
  /usr/bin/time -o "$log" -a -f "%U %S %e" "$python" -m immnet.cli track --input "$csv" --output "$work/out.csv" "$@" \
    2>/dev/null
}
one0() {  # one0(LOG): one run of BEFORE's immnet track (the default), from its checkout
  (cd "$before" && PYTHONPATH=$before one "$1")
}
[ -z "$before" ] || one0 "$work/warm"
one "$work/warm" && one "$work/warm" --method real-imm-singer --r 4
for _ in $(seq "$runs"); do
  [ -z "$before" ] || one0 "$work/a0"
  one "$work/a"
  one "$work/b" --method real-imm-singer --r 4
done
"$python" - "$work/a" "$work/b" "$work/a0" <<'PY'
import os, statistics, sys
a, b, a0 = ([list(map(float, line.split())) for line in open(path) if line.strip()] if os.path.exists(path) else None
            for path in sys.argv[1:4])
rows = (("immnet track (the default)", a), ("immnet track --method real-imm-singer --r 4", b))
for name, runs in rows + ((("the default before", a0),) if a0 else ()):
    print(f"{name:<44} median wall {statistics.median(r[2] for r in runs):6.2f} s, "
          f"median CPU {statistics.median(r[0] + r[1] for r in runs):6.2f} s")
def ratio(x, y, what):
    wall = [p[2] / q[2] for p, q in zip(x, y)]
    cpu = [(p[0] + p[1]) / (q[0] + q[1]) for p, q in zip(x, y)]
    print(f"ratio {what}, median of {len(wall)} pairs: wall {statistics.median(wall):.2f}x "
          f"({min(wall):.2f}-{max(wall):.2f}), CPU {statistics.median(cpu):.2f}x ({min(cpu):.2f}-{max(cpu):.2f})")
ratio(a, b, "default / filter")
if a0:
    ratio(a0, b, "before / filter")
    ratio(a, a0, "default / before")
PY
