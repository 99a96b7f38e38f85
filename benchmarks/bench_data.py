"""Benchmark 3D-LAST generation into a data set directory and the DataModule's batch rate.

    .venv/bin/python benchmarks/bench_data.py --n 100000 --workers 2

Targets (issue 2): 100,000 x 400 trajectories in < 60 s and < 4 GiB peak RSS on the 2-core CPU.
Writes / replaces the section ``## Data generation`` of BENCHMARKS.md at the repository root.
"""

from __future__ import annotations

import argparse
import datetime
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine, write_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SECTION = "Data generation"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=100_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--batches", type=int, default=300, help="DataModule batches to time")
    p.add_argument("--batch-size", type=int, default=100)
    p.add_argument("--out", type=Path, default=None, help="data set directory (default: a temporary one, removed)")
    p.add_argument("--no-write", action="store_true", help="do not touch BENCHMARKS.md")
    args = p.parse_args(argv)

    from immnet.data import LASTDataModule, write_dataset

    tmp = None
    out = args.out
    if out is None:
        tmp = Path(tempfile.mkdtemp(prefix="bench-data-"))
        out = tmp / "ds"
    load_before = ' '.join(f'{v:.2f}' for v in os.getloadavg())
    try:
        t0 = time.perf_counter()
        write_dataset(out, args.n, args.seed, workers=args.workers, overwrite=True, progress=True)
        gen_s = time.perf_counter() - t0
        load_after = ' '.join(f'{v:.2f}' for v in os.getloadavg())
        rss_self = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB -> GiB
        rss_child = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 2**20
        size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file()) / 2**30

        dm = LASTDataModule(out, batch_size=args.batch_size)
        loader = dm.train_dataloader()
        it = iter(loader)
        next(it)  # warm the page cache path
        t0 = time.perf_counter()
        k = 0
        for _ in range(args.batches):
            try:
                next(it)
            except StopIteration:
                it = iter(loader)
                next(it)
            k += 1
        bps = k / (time.perf_counter() - t0)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    cmd = f".venv/bin/python benchmarks/bench_data.py --n {args.n} --workers {args.workers}"
    ok_t, ok_m = gen_s < 60, max(rss_self, rss_child) < 4
    text = (
        f"`{cmd}` ({datetime.date.today().isoformat()}, commit {commit}; {machine()}; "
        f"load average {load_before} before, {load_after} after generation)\n\n"
        f"| what | value | target |\n|---|---|---|\n"
        f"| generate {args.n:,} x 400 into a memmapped dir, {args.workers} worker(s) | {gen_s:.1f} s "
        f"({args.n / gen_s:,.0f} trajectories/s) | < 60 s {'(met)' if ok_t else '(missed)'} |\n"
        f"| peak RSS, main process / largest worker | {rss_self:.2f} / {rss_child:.2f} GiB | < 4 GiB "
        f"{'(met)' if ok_m else '(missed)'} |\n"
        f"| data set size on disk (float32 floats, int64 mode) | {size:.2f} GiB | |\n"
        f"| LASTDataModule train batches of {args.batch_size} (memmap, num_workers=0) | {bps:.0f} batches/s | |\n\n"
    )
    print(text)
    if not args.no_write:
        write_section(SECTION, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
