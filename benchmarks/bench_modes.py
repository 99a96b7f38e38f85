"""What modes per group cost: IMMNet's streaming step with one set of modes, per axis and per channel.

Run:  OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_modes.py [--steps 40] [--batches 1,64,1024]
It prints a table and rewrites the ``## Modes per group`` section of BENCHMARKS.md (other sections are kept).
Each row is one model-based IMM of the registry as IMMNet with nothing learned (``IMMTracker.network()``,
float32, eager; docs/core.md "Modes per group"), the same network with ``modes`` changed and nothing else:
``real-imm``'s four models (CV, CA, two turns) joint and per channel, ``real-imm-axis``'s two (CV, CA) joint, per
channel and per axis. Per group the interaction runs the IMM's mix once per group (``FilterInteraction._mix_groups``)
and the fusion weighs each coordinate with its group's probabilities; the rest of the step is the same.
Inference as ``benchmarks/bench_immnet.py`` times it: ``IMMNet.scan`` over tracks that have started, the median of
three passes of ``--steps`` scans; the rows take turns over ``--rounds`` rounds and each reports its median round, so
that a shared machine's load falls on every row alike.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_immnet import inference  # noqa: E402
from common import rates_in_turns, rates_table, rows_arguments, write_rates  # noqa: E402

from immnet.filters.methods import build_method  # noqa: E402
from immnet.filters.trackers import _linear_network  # noqa: E402

ROWS = [("real-imm", "joint"), ("real-imm", "channel"), ("real-imm-axis", "joint"), ("real-imm-axis", "channel"),
        ("real-imm-axis", "axis")]


def network(name: str, modes: str):
    """The registry method ``name``'s IMMNet with nothing learned, with ``modes``, in float32 (r fixed at 4 m: the
    step's cost does not depend on it)."""
    m = build_method(name)
    return _linear_network(name, m.model_set, m.sigma_q, 4.0, m._p_stay, 1.0, torch.float32, modes)


def main() -> int:
    a = rows_arguments(__doc__)
    nets = [network(name, modes) for name, modes in ROWS]
    rates = rates_in_turns(nets, a, lambda net, B: inference(net, B, a.steps, net.scan))
    rows = [[f"`{name}`", str(net.n_experts), modes] for (name, modes), net in zip(ROWS, nets)]
    lines = rates_table(a, ["IMM (nothing learned)", "models", "modes"], rows, rates)
    write_rates("bench_modes.py", "Modes per group", "Track-steps/s of IMMNet's streaming step, eager, float32, each "
                "network the registry IMM's with nothing learned and only `modes` changed (docs/core.md \"Modes per "
                "group\")", a, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
