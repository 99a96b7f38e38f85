"""The motion-model family: constant velocity, constant acceleration, Singer, coordinated turn.

Each takes ``noise`` (``white``, ``wiener`` or ``continuous``: ``immnet.motion.models``) and ``vertical``, the
z axis's share of ``sigma_q`` (1: isotropic, as 3D-LAST's generator; real aircraft climb and descend more
gently than they turn)."""

from __future__ import annotations

import torch

from immnet.motion import models as m
from immnet.motion.base import MotionModel


def _args(model: MotionModel, **args) -> dict:
    """``init_args`` with ``vertical`` only where it is not the default 1 (configs written before it stay)."""
    return {**args, "noise": model.noise, **({"vertical": model.vertical} if model.vertical != 1.0 else {})}


class _Polynomial(MotionModel):
    """A model whose ``F`` is a constant-derivative block per axis (``matrix``), with its ``noise`` (None: the
    class's) and ``vertical``."""

    matrix = staticmethod(m.cv_matrix)

    def __init__(self, noise: str | None = None, vertical: float = 1.0):
        self.noise = type(self).noise if noise is None else noise
        self.vertical = m._check_vertical(vertical)

    def init_args(self) -> dict:
        return _args(self)

    def F(self, dt=1.0, dtype=torch.float64, device=None):
        return self.matrix(dt, dtype=dtype, device=device)


class ConstantVelocity(_Polynomial):
    """CV: ``F`` per axis ``[[1, dt, 0], [0, 1, 0], [0, 0, 0]]``; white-noise acceleration ``Q`` (``noise`` None:
    ``white``)."""

    mode = 0
    name = "cv"
    noise = "white"


class ConstantAcceleration(_Polynomial):
    """CA: ``F`` per axis ``[[1, dt, dt^2/2], [0, 1, dt], [0, 0, 1]]``; Wiener-process acceleration ``Q``
    (``noise`` None: ``wiener``; ``continuous``: white jerk)."""

    mode = 1
    order = 2
    name = "ca"
    noise = "wiener"
    matrix = staticmethod(m.ca_matrix)


class Singer(MotionModel):
    """Singer's model (IEEE TAES 1970): the acceleration a first-order Gauss-Markov process, ``a' = -a / tau + w``,
    ``w`` continuous white noise of spectral density ``sigma_q^2`` (the CA model's white jerk, with the acceleration
    pulled back to zero over ``tau`` seconds). ``F`` and ``Q`` exact for any interval (``immnet.motion.models.
    singer_block``, ``singer_noise``); ``tau -> inf`` is the CA model with ``noise: continuous``. An aircraft's
    accelerations are transient (a speed change, a turn's entry, a level-off): a maneuver model whose acceleration
    decays does not carry one past its end. Stands for the data mode CA."""

    mode = 1
    order = 2
    noise = "continuous"

    def __init__(self, tau: float = 20.0, vertical: float = 1.0):
        self.tau = m._check_tau(tau)
        self.vertical = m._check_vertical(vertical)

    @property
    def name(self) -> str:
        return f"singer{self.tau:g}"

    def init_args(self) -> dict:
        return {"tau": self.tau, **({"vertical": self.vertical} if self.vertical != 1.0 else {})}

    def F(self, dt=1.0, dtype=torch.float64, device=None):
        return m.singer_matrix(self.tau, dt, dtype=dtype, device=device)

    def Q(self, sigma_q: float, dt: float = 1.0, dtype=torch.float64, device=None) -> torch.Tensor:
        return m.process_noise(sigma_q, dt, self.noise, dtype=dtype, device=device, order=self.order,
                               vertical=self.vertical, tau=self.tau)


class CoordinatedTurn(MotionModel):
    """CT(w) with a fixed turn rate ``turn_rate_deg`` (deg/s); mode CT+ for ``w > 0``, CT- for ``w < 0``."""

    def __init__(self, turn_rate_deg: float = 5.0, noise: str = "white", vertical: float = 1.0):
        if turn_rate_deg == 0:
            raise ValueError("a coordinated turn needs a non-zero turn_rate_deg (use ConstantVelocity)")
        self.turn_rate_deg = float(turn_rate_deg)
        self.noise = noise
        self.vertical = m._check_vertical(vertical)
        self.mode = 2 if turn_rate_deg > 0 else 3

    @property
    def turn_rate(self) -> float:
        """Turn rate in rad/s."""
        return self.turn_rate_deg * m.DEG

    @property
    def name(self) -> str:
        return f"ct{self.turn_rate_deg:+g}"

    def init_args(self) -> dict:
        return _args(self, turn_rate_deg=self.turn_rate_deg)

    def F(self, dt=1.0, dtype=torch.float64, device=None):
        return m.ct_matrix(self.turn_rate, dt, dtype=dtype, device=device)


class AdaptiveTurn(CoordinatedTurn):
    """CT whose turn rate comes from the state it propagates: ``w = (vx ay - vy ax) / |v_h|^2``.

    In a coordinated turn the acceleration is centripetal (``a = w x v``), so a state that carries
    acceleration carries its turn rate. The rate is bounded to ``[min_deg, max_deg]`` deg/s in the
    sign of ``turn_rate_deg`` (CT+ or CT-): at the start of a turn, with no acceleration yet, the
    expert turns at the slowest rate and its gain builds the acceleration up from the innovations.
    ``turn_rate_deg`` is the nominal rate, used where a constant ``F`` is needed (a learned
    expert's steady-state gain at initialization, the analytic-gain ablation's covariance).
    Its map is ``adaptive_ct_propagate`` at its ``rate_bounds``; IMMNet's predict stage applies that map
    to all its adaptive experts at once. The model-based IMM filters need a constant ``F``
    and refuse it.
    """

    state_dependent = True

    def __init__(self, turn_rate_deg: float = 5.0, min_deg: float = 1.0, max_deg: float = 10.0, noise: str = "white"):
        super().__init__(turn_rate_deg, noise)
        if not 0 < min_deg <= abs(turn_rate_deg) <= max_deg:
            raise ValueError(
                f"AdaptiveTurn needs 0 < min_deg <= |turn_rate_deg| <= max_deg, got {min_deg}, {turn_rate_deg}, {max_deg}"
            )
        self.min_deg, self.max_deg = float(min_deg), float(max_deg)

    @property
    def name(self) -> str:
        """``ct+adaptive`` / ``ct-adaptive`` at the default bounds (1..10 deg/s, nominal 5), else
        with the bounds and nominal rate, so that two turn experts of one sign keep distinct names."""
        sign = "+" if self.turn_rate_deg > 0 else "-"
        if (self.min_deg, self.max_deg, abs(self.turn_rate_deg)) == (1.0, 10.0, 5.0):
            return f"ct{sign}adaptive"
        return f"ct{sign}adaptive{self.min_deg:g}-{self.max_deg:g}@{abs(self.turn_rate_deg):g}"

    def init_args(self) -> dict:
        return {**super().init_args(), "min_deg": self.min_deg, "max_deg": self.max_deg}

    def rate_bounds(self) -> tuple[float, float]:
        """``(lo, hi)`` turn-rate bounds in rad/s."""
        lo, hi = self.min_deg * m.DEG, self.max_deg * m.DEG
        return (lo, hi) if self.turn_rate_deg > 0 else (-hi, -lo)
