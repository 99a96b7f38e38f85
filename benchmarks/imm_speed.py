"""``imm_filter`` run REPEATS times over B tracks of T scans: a whole process to time from outside, paired against
another commit's (BENCHMARKS.md, "One eager scan loop: before and after").

Run:  env PYTHONPATH=DIR OMP_NUM_THREADS=1 .venv/bin/python benchmarks/imm_speed.py DIR B T DTYPE REPEATS
DIR is a checkout of the commit under test (on PYTHONPATH, so that its ``immnet`` is the one imported); the data and
the model set are ``benchmarks/bench_filters.py``'s (``imm3``, r 4 m, sigma_q 0.5, p_stay 0.8).
"""

import sys

import torch

torch.set_num_threads(1)
sys.path.insert(0, sys.argv[1] + "/benchmarks")
from bench_filters import _data  # noqa: E402

from immnet.config import REPO_ROOT  # noqa: E402
from immnet.filters import imm_filter, initial_state  # noqa: E402
from immnet.filters.trackers import transition_matrix  # noqa: E402
from immnet.motion import ModelSet  # noqa: E402

ms = ModelSet.from_config(str(REPO_ROOT / "configs/model_sets/imm3.yaml"))
B, T, dtype, repeats = int(sys.argv[2]), int(sys.argv[3]), getattr(torch, sys.argv[4]), int(sys.argv[5])
F, Q = ms.F(1.0, dtype=dtype), ms.Q(0.5, dtype=dtype)
M = len(ms)
Pi, mu0 = transition_matrix(0.8, M).to(dtype), torch.full((M,), 1.0 / M, dtype=dtype)
z = _data(B, T, dtype)
x0, P0 = initial_state(z, 4.0)
R = torch.tensor(16.0, dtype=dtype)
with torch.no_grad():
    for _ in range(repeats):
        imm_filter(z, x0, P0, F, Q, R, Pi, mu0)
