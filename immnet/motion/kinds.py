"""The motion-model family: constant velocity, constant acceleration, coordinated turn."""

from __future__ import annotations

import torch

from immnet.motion import models as m
from immnet.motion.base import MotionModel


class ConstantVelocity(MotionModel):
    """CV: ``F`` per axis ``[[1, dt, 0], [0, 1, 0], [0, 0, 0]]``; white-noise acceleration ``Q``."""

    mode = 0

    def __init__(self, noise: str = "white"):
        self.noise = noise

    @property
    def name(self) -> str:
        return "cv"

    def init_args(self) -> dict:
        return {"noise": self.noise}

    def F(self, dt=1.0, dtype=torch.float64, device=None):
        return m.cv_matrix(dt, dtype=dtype, device=device)


class ConstantAcceleration(MotionModel):
    """CA: ``F`` per axis ``[[1, dt, dt^2/2], [0, 1, dt], [0, 0, 1]]``; Wiener-process acceleration ``Q``."""

    mode = 1

    def __init__(self, noise: str = "wiener"):
        self.noise = noise

    @property
    def name(self) -> str:
        return "ca"

    def init_args(self) -> dict:
        return {"noise": self.noise}

    def F(self, dt=1.0, dtype=torch.float64, device=None):
        return m.ca_matrix(dt, dtype=dtype, device=device)


class CoordinatedTurn(MotionModel):
    """CT(w) with a fixed turn rate ``turn_rate_deg`` (deg/s); mode CT+ for ``w > 0``, CT- for ``w < 0``."""

    def __init__(self, turn_rate_deg: float = 5.0, noise: str = "white"):
        if turn_rate_deg == 0:
            raise ValueError("a coordinated turn needs a non-zero turn_rate_deg (use ConstantVelocity)")
        self.turn_rate_deg = float(turn_rate_deg)
        self.noise = noise
        self.mode = 2 if turn_rate_deg > 0 else 3

    @property
    def turn_rate(self) -> float:
        """Turn rate in rad/s."""
        return self.turn_rate_deg * m.DEG

    @property
    def name(self) -> str:
        return f"ct{self.turn_rate_deg:+g}"

    def init_args(self) -> dict:
        return {"turn_rate_deg": self.turn_rate_deg, "noise": self.noise}

    def F(self, dt=1.0, dtype=torch.float64, device=None):
        return m.ct_matrix(self.turn_rate, dt, dtype=dtype, device=device)
