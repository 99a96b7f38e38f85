"""The measurement update's cost per track-step: the Cartesian update of the model-based IMM's core loop
(``immnet.imm.kalman.update``, isotropic ``r`` and each detection's own ``R``) against the polar extended Kalman update
(``immnet.imm.measurement.polar_update``), on a batch of tracks x experts, float32 and float64; writes the section
"Measurement updates" of BENCHMARKS.md (``--out``)."""

from __future__ import annotations

import argparse
import datetime
import math
import statistics
import time
from pathlib import Path

import torch

from benchmarks.common import BENCHMARKS, machine, write_section
from immnet.imm.kalman import update
from immnet.imm.measurement import polar_update, to_polar


def problem(B: int, M: int, dtype, seed: int = 0):
    """Priors ``[B, M, 9]``/``[B, M, 9, 9]`` of targets 10-150 km from the radar and a plot of each (ENU and polar)."""
    g = torch.Generator().manual_seed(seed)
    rho = 10e3 + 140e3 * torch.rand(B, generator=g, dtype=torch.float64)
    az = 2 * math.pi * torch.rand(B, generator=g, dtype=torch.float64)
    el = 0.3 * torch.rand(B, generator=g, dtype=torch.float64)
    pos = torch.stack([rho * el.cos() * az.sin(), rho * el.cos() * az.cos(), rho * el.sin()], -1)
    x = torch.zeros(B, M, 9, dtype=torch.float64)
    x[..., 0::3] = pos[:, None] + 30 * torch.randn(B, M, 3, generator=g, dtype=torch.float64)
    A = torch.randn(B, M, 9, 9, generator=g, dtype=torch.float64)
    P = A @ A.transpose(-1, -2) + 100 * torch.eye(9, dtype=torch.float64)
    z = (pos + 30 * torch.randn(B, 3, generator=g, dtype=torch.float64))[:, None]
    R = torch.diag(torch.tensor([900.0, 1600.0, 2500.0], dtype=torch.float64)).expand(B, 1, 3, 3)
    sig = torch.tensor([40.0, 0.1 * math.pi / 180, 0.2 * math.pi / 180], dtype=torch.float64).expand(B, 1, 3)
    cast = lambda v: v.to(dtype).contiguous()  # noqa: E731
    return cast(x), cast(P), cast(z), cast(to_polar(z)), cast(R), cast(sig)


def timed(fn, rounds: int, inner: int) -> float:
    """The median over ``rounds`` of the seconds per call (``inner`` calls each), after a warm-up."""
    for _ in range(3):
        fn()
    out = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        out.append((time.perf_counter() - t0) / inner)
    return statistics.median(out)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tracks", type=int, default=1000)
    p.add_argument("--experts", type=int, default=4)
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--inner", type=int, default=20)
    p.add_argument("--out", type=Path, default=BENCHMARKS)
    a = p.parse_args(argv)
    torch.set_grad_enabled(False)
    B, M = a.tracks, a.experts
    rows = []
    for dtype in (torch.float32, torch.float64):
        x, P, z, plot, R, sig = problem(B, M, dtype)
        r2 = torch.tensor(900.0, dtype=dtype)
        cases = [("Cartesian, isotropic r (kalman.update)", lambda: update(x, P, z, None, r2)),
                 ("Cartesian, each detection's R (kalman.update)", lambda: update(x, P, z, None, R)),
                 ("polar EKF (polar_update)", lambda: polar_update(x, P, plot, sig)),
                 ("polar EKF, robust k = 3", lambda: polar_update(x, P, plot, sig, robust=3.0))]
        base = None
        for name, fn in cases:
            s = timed(fn, a.rounds, a.inner)
            us = s / (B * M) * 1e6
            base = base or us
            rows.append(f"| {name} | {str(dtype).removeprefix('torch.')} | {us:.3f} | {us / base:.2f} |")
            print(rows[-1], flush=True)
    text = "\n".join([
        f"`OMP_NUM_THREADS=1 PYTHONPATH=. .venv/bin/python benchmarks/bench_polar_update.py` ({datetime.date.today()}; "
        f"{machine()}). One measurement update of {B:,} tracks x {M} experts (a batch the IMM's core loop updates "
        f"at once, CPU, eager), the median of {a.rounds} rounds of {a.inner} calls; microseconds per track-step and "
        "expert, and the ratio to the isotropic Cartesian update of the same dtype. The polar update computes in "
        "float64 for float32 input (as `kalman.joseph`), so float32 saves it nothing.",
        "",
        "| update | dtype | us per track-step and expert | x Cartesian |",
        "|---|---|---:|---:|",
        *rows,
    ])
    write_section("Measurement updates", text, a.out)


if __name__ == "__main__":
    main()
