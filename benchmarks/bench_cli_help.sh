#!/bin/bash
# CPU time of the CLI's help (BENCHMARKS.md "CLI help"): each command 5 times under /usr/bin/time, the median of
# user + sys. Run from a checkout: benchmarks/bench_cli_help.sh [PYTHON] (default .venv/bin/python); the package
# measured is the checkout's (PYTHONPATH).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
python=${1:-$root/.venv/bin/python}
export PYTHONPATH=$root OMP_NUM_THREADS=1
cd "$root"  # python -m puts the working directory first on sys.path
log=$(mktemp)
trap 'rm -f "$log"' EXIT
echo "$(git -C "$root" rev-parse --short HEAD); load average $(cut -d' ' -f1-3 /proc/loadavg)"
for args in "--help" "track --help" "evaluate --help" "data generate --help"; do
  : >"$log"
  for _ in 1 2 3 4 5; do
    /usr/bin/time -o "$log" -a -f "%U %S %e" "$python" -m immnet.cli $args >/dev/null
  done
  "$python" - "$log" "immnet $args" <<'PY'
import statistics, sys
rows = [list(map(float, line.split())) for line in open(sys.argv[1]) if line.strip()]
cpu = [u + s for u, s, _ in rows]
print(f"{sys.argv[2]:<28} median CPU {statistics.median(cpu):.2f} s (user+sys: {' '.join(f'{c:.2f}' for c in cpu)}), "
      f"median wall {statistics.median(w for *_, w in rows):.2f} s")
PY
done
