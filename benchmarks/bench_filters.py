"""IMM throughput (track-steps/s) and single-track step latency, against FilterPy's IMMEstimator.

Run:  .venv/bin/python benchmarks/bench_filters.py [--steps 50] [--model-set configs/model_sets/imm3.yaml]
It prints a table and rewrites the ``## Filters`` section of BENCHMARKS.md (other sections are kept).
"""

from __future__ import annotations

import argparse
import datetime
import os
import shlex
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine, write_section  # noqa: E402

import numpy as np
import torch

from immnet.config import REPO_ROOT
from immnet.filters import imm_filter, initial_state
from immnet.filters.trackers import transition_matrix
from immnet.motion import ModelSet, measurement_matrix

BATCHES = (1, 64, 1024, 8192)


def _data(B, T, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T, dtype=torch.float64)
    pos = torch.stack([1e4 + 150 * t, -5e3 + 80 * t, 3e3 + 2 * t], -1)
    return (pos + 4 * torch.randn(B, T, 3, generator=g, dtype=torch.float64)).to(dtype)


def bench_imm(ms: ModelSet, B: int, T: int, dtype, sigma_q=0.5, r=4.0, compile=False):
    """(track-steps/s, us per step) of ``imm_filter`` over ``B`` tracks and ``T`` steps (warm-up compiles)."""
    F, Q = ms.F(1.0, dtype=dtype), ms.Q(sigma_q, dtype=dtype)
    Pi, M = transition_matrix(0.8, len(ms)).to(dtype), len(ms)
    mu0 = torch.full((M,), 1.0 / M, dtype=dtype)
    z = _data(B, T, dtype)
    x0, P0 = initial_state(z, r)
    R = torch.tensor(r * r, dtype=dtype)
    with torch.no_grad():
        imm_filter(z[:, :4], x0, P0, F, Q, R, Pi, mu0, compile=compile)  # warm-up
        t0 = time.perf_counter()
        imm_filter(z, x0, P0, F, Q, R, Pi, mu0, compile=compile)
        el = time.perf_counter() - t0
    return B * (T - 1) / el, el / (T - 1) * 1e6


def bench_filterpy(ms: ModelSet, tracks: int, T: int, sigma_q=0.5, r=4.0):
    from filterpy.kalman import IMMEstimator, KalmanFilter

    F, Q = ms.F(1.0).numpy(), ms.Q(sigma_q).numpy()
    Pi = transition_matrix(0.8, len(ms)).numpy()
    z = _data(tracks, T, torch.float64)
    x0, P0 = initial_state(z, r)
    z = z.numpy()
    t0 = time.perf_counter()
    for b in range(tracks):
        filters = []
        for Fm, Qm in zip(F, Q):
            kf = KalmanFilter(9, 3)
            kf.F, kf.Q, kf.H, kf.R = Fm, Qm, measurement_matrix().numpy(), r * r * np.eye(3)
            kf.x, kf.P = x0[b].numpy().copy(), P0[b].numpy().copy()
            filters.append(kf)
        imm = IMMEstimator(filters, np.full(len(ms), 1.0 / len(ms)), Pi)
        for zt in z[b, 1:]:
            imm.predict()
            imm.update(zt)
    el = time.perf_counter() - t0
    return tracks * (T - 1) / el, el / (tracks * (T - 1)) * 1e6


def _status(rows) -> str:
    """One line per target: met or missed, by which row (either dtype, eager or compiled)."""
    big = max((r for r in rows if r[1] >= 4096 and "IMMNet" in r[0]), key=lambda r: r[2])
    one = min((r for r in rows if r[1] == 1 and "IMMNet" in r[0]), key=lambda r: r[3])
    rate_ok, step_ok = big[2] >= 1e6, one[3] < 200
    return (
        f"Status: throughput target {'MET' if rate_ok else 'MISSED'} (best at batch >= 4096: {big[2]:,.0f} "
        f"track-steps/s, {big[0]}); single-track target {'MET' if step_ok else 'MISSED'} "
        f"(best: {one[3]:,.0f} us per step, {one[0]})."
    )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=50, help="time steps per run (default 50)")
    p.add_argument("--model-set", default="configs/model_sets/imm3.yaml")
    p.add_argument("--filterpy-tracks", type=int, default=4)
    p.add_argument("--out", type=Path, default=REPO_ROOT / "BENCHMARKS.md")
    p.add_argument("--no-write", action="store_true")
    p.add_argument("--section", default="Filters", help="BENCHMARKS.md section to (re)write (default: Filters)")
    args = p.parse_args(argv)
    ms = ModelSet.from_config(args.model_set)
    rows = []
    for compile in (False, True):
        for dtype in (torch.float64, torch.float32):
            for B in BATCHES:
                T = args.steps if B > 1 else 4 * args.steps
                rate, us = bench_imm(ms, B, T, dtype, compile=compile)
                rows.append((f"IMMNet imm_filter{', compile=True' if compile else ''}, {str(dtype)[6:]}", B, rate, us))
                print(f"{rows[-1][0]:46s} B={B:5d} {rate:12,.0f} track-steps/s {us:10.0f} us/step", flush=True)
    rate, us = bench_filterpy(ms, args.filterpy_tracks, args.steps)
    rows.append(("FilterPy IMMEstimator, float64", 1, rate, us))
    print(f"{rows[-1][0]:46s} B={1:5d} {rate:12,.0f} track-steps/s {us:10.0f} us/step")
    env = " ".join(f"{k}={v}" for k, v in sorted(os.environ.items())  # glibc tuning, threads
                   if k.startswith("MALLOC_") or k == "OMP_NUM_THREADS")
    cmd = f"{env} PYTHONPATH=. .venv/bin/python benchmarks/bench_filters.py " + shlex.join(argv if argv is not None else sys.argv[1:])
    lines = [
        f"IMM with {len(ms)} models ({', '.join(ms.names)}), {args.steps} steps (batch 1: {4 * args.steps}), "
        f"{datetime.date.today().isoformat()}; {machine()}.",
        f"Command: `{cmd.strip()}`",
        "",
        "| implementation | batch | track-steps/s | us per step (whole batch) |",
        "|---|---:|---:|---:|",
        *[f"| {name} | {B} | {rate:,.0f} | {us:,.0f} |" for name, B, rate, us in rows],
        "",
        "Targets: >= 1,000,000 track-steps/s at batch >= 4096 (3 models) and < 200 us per single-track step.",
        _status(rows),
        "compile=True: torch.compile (inductor) of `immnet/filters/imm_fused.py`; its compile time (seconds, the "
        "first call per dtype) is in the untimed warm-up. At large batch part of its step is page faults on the "
        "fresh covariance buffers of each step, which glibc returns to the OS; raising MALLOC_MMAP_THRESHOLD_ and "
        "MALLOC_TRIM_THRESHOLD_ (a process-wide setting the library leaves alone) keeps them: the section "
        "'Filters, glibc malloc tuned' is that run.",
    ]
    if not args.no_write:
        write_section(args.section, "\n".join(lines), args.out)
        print(f"wrote the {args.section} section of {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
