"""Fresh views of each training batch: the same flights seen from another heading with new measurement noise.

A real-flight training set is a few hundred windows of one region, each measured once (``immnet data adsb``): a
network that passes over it many times can learn that region's headings and the very noise draws of its windows.
``FlightAugment`` gives each training batch a view of its own, drawn from a generator seeded by the training step
(so a resumed run sees the views an uninterrupted one sees):

- ``rotate``: each track's truth (position, velocity, acceleration) turned about the radar site's vertical by an
  angle drawn uniformly from ``[0, 2 pi)``: what the same motion is on another heading. The vertical, the range
  from the site, speeds and turn rates are unchanged; so are the mode labels (a rotation does not change a turn's
  sense). Without ``renoise`` the measurements turn with the truth (isotropic noise keeps its law under a turn).
- ``renoise``: new measurements of the (turned) truth, ``z = H x + r e``, ``e ~ N(0, I3)``, each track's ``r``
  drawn from ``U[r_range]`` (None: the track's own ``r``) and written to the batch's ``r``; the scans missed in the
  data stay missed. This is the measurement model of every data set the package writes, 3D-LAST's and
  ``immnet data adsb``'s (docs/data.md).
- ``turns``: the share of tracks flown through added turns (:func:`add_turns`): the window cut into segments of
  ``turn_segment`` seconds, each flown straight (as recorded) or, with probability one half, turning (either sense)
  at the rate of a coordinated turn banked ``turn_bank`` degrees at the track's mean speed, ``g tan(bank) / v``
  (30 deg at 100 m/s: 3.2 deg/s; at 230 m/s: 1.4 deg/s), rolling from one rate to the next in ``ROLL_S`` seconds.
  Each track keeps its own speed profile, vertical profile and turns; on top of them it flies orbits, racetracks and
  S-turns, which the training flights of one region hold few of (docs/notebook/real-flights.md, "Turns added to the
  training flights"). Its draws come from a generator of their own, so ``rotate`` and ``renoise`` draw the same views
  with and without it.

Validation and test batches are never changed. ``LASTDataModule(augment=...)`` applies it (docs/training.md).
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict

from immnet import keys
from immnet.data.contract import NO_LABEL
from immnet.data.times import scan_intervals
from immnet.motion.models import ACC, POS, VEL, turn_rate_of


class FlightAugment:
    """``rotate`` and ``renoise`` as the module says; ``r_range``: ``[r_min, r_max]`` (m) of the new measurement
    noise, None: each track's own ``r``; ``seed``: with the training step, the generator's seed."""

    def __init__(self, rotate: bool = True, renoise: bool = True, r_range: tuple[float, float] | None = None,
                 seed: int = 0, turns: float = 0.0, turn_bank: tuple[float, float] = (10.0, 30.0),
                 turn_segment: tuple[float, float] = (20.0, 120.0)):
        if r_range is not None:
            r_range = _range("r_range", r_range, "m; or None")
            if not renoise:
                raise ValueError("r_range draws new measurement noise: it needs renoise=True")
        if not (math.isfinite(float(turns)) and 0.0 <= float(turns) <= 1.0):
            raise ValueError(f"turns is the share of tracks given added turns, in [0, 1], got {turns!r}")
        if float(turns) > 0 and not renoise:
            raise ValueError("turns changes each turned track's truth: it needs renoise=True to measure it again")
        self.turn_bank = _range("turn_bank", turn_bank, "deg")
        if self.turn_bank[1] >= 90:
            raise ValueError(f"turn_bank must be below 90 deg, got {turn_bank!r}")
        self.turn_segment = _range("turn_segment", turn_segment, "s")
        self.rotate, self.renoise, self.r_range, self.seed = bool(rotate), bool(renoise), r_range, int(seed)
        self.turns = float(turns)

    def __repr__(self) -> str:
        return (f"FlightAugment(rotate={self.rotate}, renoise={self.renoise}, r_range={self.r_range}, "
                f"seed={self.seed}, turns={self.turns}, turn_bank={self.turn_bank}, turn_segment={self.turn_segment})")

    def __call__(self, batch: TensorDict, step: int) -> TensorDict:
        """The view of ``batch`` (any leading batch dims, time second to last) for training step ``step``."""
        if not (self.rotate or self.renoise):
            return batch
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + int(step))
        out = batch.copy()  # shallow: the tensors it changes are replaced, never written in place
        states = out[keys.STATES]
        z = out[keys.MEASUREMENTS]
        lead = states.shape[:-2]
        if self.turns > 0:
            if keys.MODE in out.keys() and bool((out[keys.MODE] != NO_LABEL).any()):
                raise ValueError("FlightAugment(turns > 0) is for flights without mode labels (immnet data adsb): "
                                 "the added turns would contradict this batch's 'mode' labels")
            states = self._turned(out, int(step))
            out[keys.STATES] = states
        if self.rotate:
            theta = torch.rand(lead, generator=g, dtype=torch.float64) * (2 * math.pi)
            c, s = theta.cos()[..., None], theta.sin()[..., None]
            turned = states.to(torch.float64, copy=True)  # in float64: positions are ~1e5 m from the site
            for ix, iy in zip((POS[0], VEL[0], ACC[0]), (POS[1], VEL[1], ACC[1])):
                turned[..., ix], turned[..., iy] = _rotated(c, s, turned[..., ix].clone(), turned[..., iy].clone())
            states = turned.to(states.dtype)
            out[keys.STATES] = states
            if not self.renoise:
                x, y = _rotated(c, s, z[..., 0].to(torch.float64), z[..., 1].to(torch.float64))
                z = torch.stack([x.to(z.dtype), y.to(z.dtype), z[..., 2]], -1)
        if self.renoise:
            if self.r_range is None:
                if keys.R not in out.keys():
                    raise ValueError("FlightAugment(renoise=True, r_range=None) measures each track again with its own "
                                     "r, and this batch holds no 'r': give r_range")
                r = out[keys.R].to(torch.float64)
            else:
                lo, hi = self.r_range
                r = lo + (hi - lo) * torch.rand(lead, generator=g, dtype=torch.float64)
                out[keys.R] = r.to(out[keys.R].dtype if keys.R in out.keys() else states.dtype)
            e = torch.randn(*states.shape[:-1], 3, generator=g, dtype=torch.float64)
            fresh = (turned if self.rotate else states.to(torch.float64))[..., list(POS)] + r[..., None, None] * e
            z = torch.where(torch.isnan(z), z, fresh.to(z.dtype))
        out[keys.MEASUREMENTS] = z
        if keys.MEAS_COV in out.keys():  # each detection's covariance follows its measurement
            cov = out[keys.MEAS_COV]
            if self.renoise:
                fresh_cov = (r * r)[..., None, None, None] * torch.eye(3, dtype=torch.float64)
                cov = torch.where(torch.isnan(z).any(-1)[..., None, None], float("nan"), fresh_cov).to(cov.dtype)
            else:  # turned about the vertical: C' = Rot C Rot^T
                zero, one = torch.zeros_like(c), torch.ones_like(c)
                rot = torch.stack([torch.cat([c, -s, zero], -1), torch.cat([s, c, zero], -1),
                                   torch.cat([zero, zero, one], -1)], -2)[..., None, :, :]
                cov = (rot @ cov.to(torch.float64) @ rot.transpose(-1, -2)).to(cov.dtype)
            out[keys.MEAS_COV] = cov
        if self.turns > 0 and keys.TURN_RATE in out.keys():
            # the data writer's turn_rate (immnet.data.real.turn_rate: a floor of 1e-9 m^2/s^2 on the speed squared)
            rate = turn_rate_of(out[keys.STATES].to(torch.float64), min_speed=_WRITER_MIN_SPEED)
            out[keys.TURN_RATE] = rate.to(out[keys.TURN_RATE].dtype)
        return out

    def _turned(self, batch: TensorDict, step: int) -> torch.Tensor:
        """``batch``'s truth with added turns on a share ``turns`` of its tracks (``states``' dtype)."""
        g = torch.Generator().manual_seed(_TURN_SEED + self.seed * 1_000_003 + step)
        states = batch[keys.STATES]
        lead, T = states.shape[:-2], states.shape[-2]
        flat = batch.reshape(-1) if len(lead) != 1 else batch
        intervals = scan_intervals(flat)  # [N, T]
        N = intervals.shape[0]
        span = float(intervals[:, 1:].sum(-1).max()) if T > 1 else 0.0
        lo, hi = self.turn_segment
        K = int(math.ceil(span / lo)) + 2  # segments enough to cover the longest window
        lengths = lo + (hi - lo) * torch.rand(N, K, generator=g, dtype=torch.float64)
        offset = lengths[:, :1] * torch.rand(N, 1, generator=g, dtype=torch.float64)
        boundaries = lengths.cumsum(-1) - offset  # b_0 in [0, first length]: the window starts inside a segment
        x = states.reshape(N, T, states.shape[-1]).to(torch.float64)
        speed = x[..., [VEL[0], VEL[1]]].norm(dim=-1).mean(-1, keepdim=True).clamp(min=1.0)  # [N, 1]
        b_lo, b_hi = (math.radians(v) for v in self.turn_bank)
        bank = b_lo + (b_hi - b_lo) * torch.rand(N, K + 1, generator=g, dtype=torch.float64)
        size = G * bank.tan() / speed
        sense = torch.where(torch.rand(N, K + 1, generator=g) < 0.5, -1.0, 1.0).to(torch.float64)
        turning = torch.rand(N, K + 1, generator=g) < 0.5
        chosen = torch.rand(N, generator=g) < self.turns
        rates = torch.where(turning & chosen[:, None], sense * size, torch.zeros((), dtype=torch.float64))
        turned = torch.where(chosen[:, None, None], add_turns(x, intervals, boundaries, rates), x)
        return turned.reshape(states.shape).to(states.dtype)


G = 9.80665
"""Standard gravity (m/s^2): a coordinated turn banked ``phi`` at speed ``v`` turns at ``G tan(phi) / v``."""

_TURN_SEED = 0x5EED_0000_0000
"""Offsets the added turns' generator from the views' (``seed * 1_000_003 + step``)."""

_WRITER_MIN_SPEED = 1e-9 ** 0.5
"""``turn_rate_of``'s speed floor that gives ``immnet.data.real.turn_rate``'s (the speed squared at least 1e-9)."""

ROLL_S = 5.0
"""Seconds in which an added turn's rate goes from one segment's to the next (linearly): an airliner rolls into a
rate-one turn (25-30 deg of bank) in about five seconds."""


def _rotated(c, s, x, y):
    """``(x, y)`` turned by the angle of cosine ``c`` and sine ``s`` (counterclockwise)."""
    return c * x - s * y, s * x + c * y


def _range(name: str, value, unit: str) -> tuple[float, float]:
    if len(value) != 2 or not all(math.isfinite(float(v)) for v in value) or not 0 < float(value[0]) <= float(value[1]):
        raise ValueError(f"{name} must be [low, high] with 0 < low <= high ({unit}), got {value!r}")
    return float(value[0]), float(value[1])


def _turn_phase(tau: torch.Tensor, boundaries: torch.Tensor, rates: torch.Tensor):
    """The added rate ``w(tau)`` and heading ``phi(tau) = integral_0^tau w`` at times ``tau [N, S]``: ``rates[:, 0]``
    from ``tau = 0``, going to ``rates[:, k + 1]`` linearly over ``ROLL_S`` seconds from ``boundaries[:, k]``."""
    u = (tau[..., None] - boundaries[:, None, :]) / ROLL_S  # [N, S, K]
    step = (rates[:, 1:] - rates[:, :-1])[:, None, :]
    ramp = u.clamp(0.0, 1.0)
    area = torch.where(u >= 1.0, u - 0.5, 0.5 * u.clamp(min=0.0) ** 2)  # integral of the ramp, in units of ROLL_S
    w = rates[:, :1] + (step * ramp).sum(-1)
    phi = rates[:, :1] * tau + ROLL_S * (step * area).sum(-1)
    return w, phi


def add_turns(states: torch.Tensor, intervals: torch.Tensor, boundaries: torch.Tensor,
              rates: torch.Tensor) -> torch.Tensor:
    """States ``[N, T, 9]`` (float64) flown with an added turn rate: the horizontal velocity turned by the added
    heading ``phi(t)`` (``_turn_phase``; ``t`` from scan 0, ``intervals [N, T]`` as ``scan_intervals`` gives them),
    the acceleration ``R(phi) a + w J R(phi) v`` (its derivative), the positions from scan 0 on by each step of the
    recorded flight turned by the heading at mid-step, with the step's cubic (Hermite) integral of the new velocity
    in place of the old's: a straight flight becomes an arc of radius ``v / w``; a flight with no added rate is
    itself. The vertical is unchanged."""
    tau = torch.cat([torch.zeros_like(intervals[:, :1]), intervals[:, 1:].cumsum(-1)], -1)
    w, phi = _turn_phase(tau, boundaries, rates)
    dt = intervals[:, 1:]
    _, phi_mid = _turn_phase(tau[:, :-1] + 0.5 * dt, boundaries, rates)

    out = states.clone()
    c, s = phi.cos(), phi.sin()
    vx, vy = _rotated(c, s, states[..., VEL[0]], states[..., VEL[1]])
    ax, ay = _rotated(c, s, states[..., ACC[0]], states[..., ACC[1]])
    out[..., VEL[0]], out[..., VEL[1]] = vx, vy
    out[..., ACC[0]], out[..., ACC[1]] = ax - w * vy, ay + w * vx

    def hermite(v, a):  # integral of the cubic through (v, a) at both ends of each step
        return 0.5 * dt * (v[:, :-1] + v[:, 1:]) + dt * dt / 12.0 * (a[:, :-1] - a[:, 1:])

    old = [hermite(states[..., VEL[i]], states[..., ACC[i]]) for i in (0, 1)]
    new = [hermite(out[..., VEL[i]], out[..., ACC[i]]) for i in (0, 1)]
    dx, dy = (states[:, 1:, POS[i]] - states[:, :-1, POS[i]] - old[i] for i in (0, 1))  # what the cubic misses
    dx, dy = _rotated(phi_mid.cos(), phi_mid.sin(), dx, dy)
    for i, d in zip((0, 1), (dx, dy)):
        out[:, 1:, POS[i]] = states[:, :1, POS[i]] + (new[i] + d).cumsum(-1)
    return out
