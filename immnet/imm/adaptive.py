"""Adaptive process noise: a per-track scale of the white-acceleration noise, by covariance matching.

A filter whose process noise is too small is too confident: its innovations ``nu_t`` are larger than
its own innovation covariance ``S_t`` says, and the normalized innovation squared
``eps_t = nu_t^T S_t^-1 nu_t`` averages above its expected value ``m`` (the measurement's dimension;
``eps ~ chi^2_m`` for a consistent filter). ``AdaptiveNoise`` keeps, per track, a scale ``lambda`` of
the process noise ``Q`` and moves it so that the mean NIS matches ``m`` (covariance matching on the
innovations, Mehra 1972; Bar-Shalom, Li & Kirubarajan 2001, chapter 11), by a stochastic
approximation on ``log lambda`` with exponential forgetting:

    ``log lambda_t = clip(log lambda_{t-1} + rate * (min(eps_t / m, nis_clip) - 1 - deadband), 0, log max_scale)``

on every scan with a measurement (``eps_t`` computed with ``lambda_{t-1}``, the scale the scan's
prediction used). Its fixed point is where ``E[min(eps / m, nis_clip)] = 1 + deadband``: with
``deadband = 0`` and no clipping, the scale at which the filter is consistent, i.e. the true ratio of
the process noise to the assumed one (tests/test_adaptive.py checks it against the closed-form
steady state of a scalar Kalman filter). ``rate`` is the forgetting (a memory of about ``1 / rate``
scans); ``nis_clip`` keeps one maneuver onset's huge innovation from jumping the scale (the IMM's
mode switch handles that); ``deadband`` leaves the scale at 1 on data where the assumed noise holds
but maneuvers make the innovations a little heavy-tailed; ``lambda`` never falls below 1, so the
filter only ever gets less confident than designed, and never more than ``max_scale`` times.

The filters that use it (``immnet.filters.IMMEKF(adapt=...)``, IMMNet's filter experts
``immnet.stages.filtering``) scale the white-acceleration part of each mode-matched filter's ``Q``
by the track's ``lambda`` and feed it the smallest NIS of their mode-matched filters: the scale grows
only when every mode's filter is too confident (too little process noise), not when one mode is the
wrong one (a maneuver, which the IMM's mode switch handles) (docs/baselines.md, docs/immnet.md
"Adaptive process noise").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from immnet.imm.option import Option


@dataclass(frozen=True)
class AdaptiveNoise(Option):
    """The adaptation rule's settings (module doc); ``True`` in a config means these defaults."""

    ARG = "adapt"

    rate: float = 0.02  # forgetting: a memory of ~50 scans
    deadband: float = 0.15  # mean NIS / m above 1 + deadband before the scale grows
    nis_clip: float = 4.0  # one scan's NIS / m counts at most this much
    max_scale: float = 100.0  # lambda in [1, max_scale]
    dim: int = 3  # m, the measurement's dimension

    def __post_init__(self):
        if not (0.0 < self.rate < 1.0):
            raise ValueError(f"AdaptiveNoise.rate must be in (0, 1), got {self.rate}")
        if not (0.0 <= self.deadband < self.nis_clip - 1.0):
            raise ValueError(f"AdaptiveNoise.deadband must be >= 0 and below nis_clip - 1, got {self.deadband}")
        if not (math.isfinite(self.max_scale) and self.max_scale >= 1.0):
            raise ValueError(f"AdaptiveNoise.max_scale must be finite and >= 1, got {self.max_scale}")
        if not (isinstance(self.dim, int) and self.dim >= 1):
            raise ValueError(f"AdaptiveNoise.dim must be an int >= 1, got {self.dim}")

    @staticmethod
    def scale(log_scale: torch.Tensor) -> torch.Tensor:
        """``lambda = exp(log lambda)``."""
        return torch.exp(log_scale)

    def update(self, log_scale: torch.Tensor, nis: torch.Tensor, measured: torch.Tensor) -> torch.Tensor:
        """``log lambda_t`` from ``log lambda_{t-1}`` and this scan's NIS (unchanged where ``measured`` is
        False or the NIS is not finite)."""
        step = self.rate * (torch.clamp(nis / self.dim, max=self.nis_clip) - 1.0 - self.deadband)
        ok = measured & torch.isfinite(nis)
        new = torch.clamp(log_scale + torch.where(ok, step, torch.zeros_like(step)), 0.0, math.log(self.max_scale))
        return torch.where(ok, new, log_scale)
