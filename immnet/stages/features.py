"""Feature scaling shared by the stages: a signed log over a fixed scale.

KalmanNet's L2 normalization throws the magnitude away; ``slog(f / s) = sign(f) log(1 + |f| / s)``
keeps it, is O(1) for the magnitudes that matter, and grows only logarithmically for outliers.
Scales (docs/spec.md section 6): F1 /100 m, F2 /10 m, F3 /[100 m, 10 m/s, 1 m/s^2], F4 /[10, 1, 0.1].
"""

from __future__ import annotations

import torch


def slog(x: torch.Tensor, scale) -> torch.Tensor:
    """Signed log ``sign(x) log1p(|x| / scale)``; NaN-free for finite input."""
    y = x / scale
    return torch.sign(y) * torch.log1p(y.abs())


def state_scale(pos: float, vel: float, acc: float) -> torch.Tensor:
    """A ``[9]`` scale vector in the state layout ``[l, v, a] x 3``."""
    return torch.tensor([pos, vel, acc] * 3)


F1_SCALE = 100.0
F2_SCALE = 10.0
F3_SCALE = (100.0, 10.0, 1.0)
F4_SCALE = (10.0, 1.0, 0.1)
