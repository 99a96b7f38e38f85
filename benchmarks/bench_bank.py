"""What the bank of networks costs (the default tracker): its streaming step against the general network's alone.

Run:  OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_bank.py [--steps 40] [--batches 1,64,1024]
It prints a table and rewrites the ``## The bank of networks`` section of BENCHMARKS.md (other sections are kept).
The rows: the shipped general network alone (``IMMNet.scan``, what ``Tracker.pretrained("general").step`` runs) at
1 s and at 5 s scans, and the shipped bank (``Tracker.pretrained()``, ``immnet.tracking.bank.NetworkBank.step``:
each member's scan, its predictive likelihood and the mixture; docs/tracking.md "A bank of networks") at 1 s (the
general, real-flight 1 s and 3D-LAST networks run), 3 s (the general network alone in the bank), 5 s (the general,
real-5s and real-4.5-12s networks), 8 s (the general and real-4.5-12s networks) and 11.5 s (the general, real-11s and
real-4.5-12s networks). Tracks that have started, the median of three passes of ``--steps`` scans; the rows take
turns over ``--rounds`` rounds and each reports its median round.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_immnet import inference, median_seconds, scans  # noqa: E402
from common import rates_in_turns, rates_table, rows_arguments, write_rates  # noqa: E402

from immnet.tracking.bank import NetworkBank  # noqa: E402
from immnet.tracking.tracker import Tracker  # noqa: E402

ROWS = (("general", 1.0), ("general", 5.0), ("bank", 1.0), ("bank", 3.0), ("bank", 5.0), ("bank", 8.0), ("bank", 11.5))
LABELS = {"general": "the general network alone", "bank": "the bank (the default)"}


def general_rate(net, B: int, steps: int, dt: float) -> float:
    """Track-steps/s of ``net.scan`` at scans ``dt`` apart (its own step at its nominal 1 s)."""
    interval = None if dt == net.dt else torch.full((B,), dt)
    return inference(net, B, steps, lambda carry, z: net.scan(carry, z, interval=interval))


def bank_rate(bank: NetworkBank, B: int, steps: int, dt: float) -> float:
    """Track-steps/s of ``bank.step`` at scans ``dt`` apart, from the same state each pass."""
    z = scans(B, steps + 5)
    bank.reset(B)
    for t in range(5):  # start the tracks, warm up
        bank.step(z[:, t], dt=dt)
    carries, log_w = dict(bank.carries), bank.log_w.clone()

    def timed_pass():
        bank.carries, bank.log_w = dict(carries), log_w.clone()
        for t in range(5, steps + 5):
            bank.step(z[:, t], dt=dt)

    return B * steps / median_seconds(timed_pass, 3)


def main() -> int:
    a = rows_arguments(__doc__)
    general, bank = Tracker.pretrained("general").net, Tracker.pretrained()
    rows = [(general if name == "general" else bank, name, dt) for name, dt in ROWS]

    def rate(row, B):
        obj, name, dt = row
        return general_rate(obj, B, a.steps, dt) if name == "general" else bank_rate(obj, B, a.steps, dt)

    with torch.no_grad():
        rates = rates_in_turns(rows, a, rate)
    lines = rates_table(a, ["step", "scans"], [[LABELS[name], f"{dt:g} s"] for name, dt in ROWS], rates)
    write_rates("bench_bank.py", "The bank of networks", "Track-steps/s of the streaming step, eager, float32: the shipped "
                "general network alone and the shipped bank of networks, the default tracker (docs/tracking.md \"A bank "
                "of networks\"), at the scan intervals that decide which members run", a, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
