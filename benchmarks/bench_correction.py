"""What the output correction costs: IMMNet's streaming step of the three-filter decoupled IMM with and without it.

Run:  OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_correction.py [--steps 40] [--batches 1,64,1024]
It prints a table and rewrites the ``## The output correction`` section of BENCHMARKS.md (other sections are kept).
The rows are ``real-imm-singer`` as IMMNet with nothing learned (``PerAxisIMMTracker.network()``, float32, eager,
r fixed at 4 m: the step's cost does not depend on it) and the same network with an output correction of 2 GRU
layers of 64 and of 128 units (``immnet.stages.correct.OutputCorrection``, untrained: its cost does not depend on
its weights; docs/immnet.md "The output correction"), three of 2 x 128 averaged (``CorrectionEnsemble``), and the
shipped ``real`` and ``real-5s`` networks as a user runs them (``real``: that filter and three 2 x 128 corrections,
each track's r estimated from its measurements; ``real-5s``: the same on the filter tuned at 4.5-5.5 s). Inference as
``benchmarks/bench_immnet.py`` times it: ``IMMNet.scan`` over tracks that have started, the median of three passes of
``--steps`` scans; the rows take turns over ``--rounds`` rounds and each reports its median round.
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
from immnet.stages import IMMNet  # noqa: E402

HIDDEN = (None, 64, 128, "3x128", "real", "real-5s")
LABELS = {None: "`real-imm-singer` (nothing learned)",
          "3x128": "with three output corrections of 2 x 128 GRU units, averaged",
          "real": "the shipped `real` (three corrections of 2 x 128, r estimated)",
          "real-5s": "the shipped `real-5s` (three corrections of 2 x 128 on `real-imm-singer-5s`, r estimated)"}
"""Each row's label in BENCHMARKS.md; a number of units: one correction of that size."""


def network(hidden: int | str | None) -> IMMNet:
    """``real-imm-singer``'s step (r fixed at 4 m, float32) with an output correction of ``hidden`` units, or none,
    or (``"3x128"``) three corrections of 128 averaged (``CorrectionEnsemble``); ``"real"``, ``"real-5s"``: the
    shipped network of that name (``real-5s`` scanned at its nominal interval, 5 s)."""
    if hidden in ("real", "real-5s"):
        from immnet.checkpoints import shipped
        from immnet.tracking.tracker import load_network

        return load_network(shipped(hidden)).float().eval()
    m = build_method("real-imm-singer")
    base = _linear_network(m.name, m.model_set, m.sigma_q, 4.0, m._p_stay, 1.0, torch.float32, "axis")
    if hidden is None:
        return base
    correction = ({"class_path": "immnet.stages.correct.CorrectionEnsemble", "init_args": {"members": 3, "hidden": 128}}
                  if hidden == "3x128" else
                  {"class_path": "immnet.stages.correct.OutputCorrection", "init_args": {"hidden": hidden}})
    return IMMNet(**base.config, correction=correction).eval()


def main() -> int:
    a = rows_arguments(__doc__)
    nets = [network(h) for h in HIDDEN]
    with torch.no_grad():
        rates = rates_in_turns(nets, a, lambda net, B: inference(net, B, a.steps, net.scan))
    rows = [[LABELS.get(h, f"with an output correction, 2 x {h} GRU units")] for h in HIDDEN]
    lines = rates_table(a, ["step"], rows, rates)
    write_rates("bench_correction.py", "The output correction", "Track-steps/s of IMMNet's streaming step, eager, "
                "float32: the three-filter decoupled IMM with nothing learned, and with the output correction after its "
                "fusion (docs/immnet.md \"The output correction\"), one or three of them, and the shipped `real` and "
                "`real-5s` networks", a, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
