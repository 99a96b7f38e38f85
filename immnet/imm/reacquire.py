"""Re-acquisition: a track that its detections have left restarts from them.

A robust update (``immnet.imm.kalman``, Huber's) moves a track at most ``k`` standard deviations towards an isolated
detection it cannot explain and takes the next far one by the plain gain. That is right for an outlier and for a
maneuver, and slow for a track that is itself off: a track started on an outlier, or taken off by one before its
velocity was known, or coasted through a maneuver, is pulled back by the Kalman gain over several scans. The radar engineer's rule: a detection far outside every
filter's gate is set aside, and after ``scans`` consecutive such detections that agree with one another (each within
``speed`` of the one before it horizontally and ``climb`` vertically, over the time between them, to three standard
deviations of the two plots' noise) the track restarts at the last of them as at its first detection (its position that plot's, its covariance the plot's,
the velocity and acceleration unknown, the modes the filters' prior). A detection inside some filter's gate clears the
run; a missed scan leaves it as it is (the time between the plots grows). A far detection that the target could have
reached (some filter's prediction plus its largest accelerations over the interval: ``reachable``) is not set aside,
though it counts for the run: a maneuver sharper than the filters' models puts plots there, an outlier mostly not.

``Reacquire`` is the setting (``IMMTracker(reacquire=...)``, ``FilterGain(reacquire=...)``); ``Watch`` the state
each track carries, ``advance`` one scan of it, the same function in the model-based scan loop
(``immnet.imm.runner.run``) and in IMMNet's filter experts (``immnet.stages.filtering``), so the two runtimes
restart the same tracks at the same scans. Where no track restarts nothing changes, bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch

from immnet.imm.kalman import _as_cov, inv3, quadratic, start_state
from immnet.imm.option import Option, is_number, positive


@dataclass(frozen=True)
class Reacquire(Option):
    """Re-acquisition's setting (module doc); the defaults are the radar IMMs' (``radar-imm-robust-5s``, ``-11s``),
    chosen on the training and validation flights (docs/radar.md, "Re-acquisition, measured").

    ``scans``: how many consecutive far detections restart a track (>= 2: the run's consistency needs two);
    ``gate``: the squared Mahalanobis distance ``d^2 = nu^T S^-1 nu`` beyond which a detection is far, for every filter
    of the track (a chi-square with 3 degrees of freedom exceeds 25 with probability 1.5e-5, 50 with 1e-10);
    ``speed``, ``climb``: the largest horizontal and vertical speeds (m/s) between two detections that agree;
    ``reject``: a far detection that does not restart the track is not filtered (a gate: the filters predict through
    it as through a missed scan), else the update takes it (Huber's, where the filter has one); ``accel``,
    ``vertical_accel``: the target's largest horizontal and vertical accelerations (m/s^2): a far detection within
    their reach (``reachable``) is not rejected, for a maneuver the filters' models do not hold puts it there (None:
    every far detection is rejected)."""

    ARG = "reacquire"
    scans: int = 2
    gate: float = 25.0
    speed: float = 300.0
    climb: float = 50.0
    reject: bool = True
    accel: float | None = 60.0
    vertical_accel: float | None = 2.0

    def __post_init__(self):
        if isinstance(self.scans, bool) or not isinstance(self.scans, int) or self.scans < 2:
            raise ValueError(f"reacquire's scans must be an integer >= 2 (consecutive far detections), got {self.scans!r}")
        if not isinstance(self.reject, bool):
            raise ValueError(f"reacquire's reject must be true or false, got {self.reject!r}")
        for name in ("gate", "speed", "climb"):
            positive(getattr(self, name), f"reacquire's {name} must be a finite number > 0")
        if (self.accel is None) != (self.vertical_accel is None):
            raise ValueError(f"reacquire's accel and vertical_accel are both numbers or both None (every far detection "
                             f"rejected), got {self.accel!r} and {self.vertical_accel!r}")
        for name in ("accel", "vertical_accel"):
            value = getattr(self, name)
            if value is not None and not (is_number(value) and value >= 0):
                raise ValueError(f"reacquire's {name} must be a finite number >= 0 (m/s^2) or None, got {value!r}")


class Watch(NamedTuple):
    """What each track carries for re-acquisition: ``count [B]`` (in the state's dtype) -1 while the track waits for the
    detection that confirms its start, else the length of its run of far detections; ``plot [B, 3]`` the start's
    detection or the run's last, ``cov [B, 3, 3]`` its covariance, ``elapsed [B]`` the time since it (s)."""

    count: torch.Tensor
    plot: torch.Tensor
    cov: torch.Tensor
    elapsed: torch.Tensor


def watch(batch: int, dtype=torch.float64, device=None) -> Watch:
    """The watch of ``batch`` tracks that have not started."""
    return Watch(torch.full((batch,), -1.0, dtype=dtype, device=device), torch.zeros(batch, 3, dtype=dtype, device=device),
                 torch.zeros(batch, 3, 3, dtype=dtype, device=device), torch.zeros(batch, dtype=dtype, device=device))


def started(z: torch.Tensor, R: torch.Tensor) -> Watch:
    """The watch of tracks that start at the detections ``z [B, 3]`` with covariances ``R [B, 3, 3]``."""
    return Watch(torch.full(z.shape[:1], -1.0, dtype=z.dtype, device=z.device), z.clone(), R.to(z.dtype).clone(),
                 torch.zeros(z.shape[:1], dtype=z.dtype, device=z.device))


def innovations(z: torch.Tensor, x: torch.Tensor, P: torch.Tensor, R: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each filter's innovation of the detection ``z [B, 3]`` from its prediction ``x [B, M, 9]``, ``P [B, M, 9, 9]``
    (the position's rows 0, 3, 6) with the measurement covariance ``R [B, 3, 3]``: ``(nu [B, M, 3], S [B, M, 3, 3])``,
    what the squared Mahalanobis distances (``kalman.quadratic``) and ``reachable`` read."""
    return z[:, None, :] - x[..., 0::3], P[..., 0::3, 0::3] + R[:, None]


def reachable(rule: Reacquire, nu: torch.Tensor, S: torch.Tensor, interval) -> torch.Tensor:
    """The tracks ``[B]`` (bool) whose detection some filter reaches with the rule's accelerations over ``interval`` (a
    number or ``[B]``, s), from each filter's innovation ``nu [B, M, 3]`` and its covariance ``S [B, M, 3, 3]`` (the
    prediction's and the plot's, ``innovations``): the horizontal distance within ``accel dt^2 / 2`` plus three
    standard deviations there (``sqrt`` of ``S``'s horizontal trace), the vertical within ``vertical_accel dt^2 / 2``
    plus three of its vertical ones. None of them where the rule has no accelerations."""
    if rule.accel is None:
        return torch.zeros(nu.shape[0], dtype=torch.bool, device=nu.device)
    dt = torch.as_tensor(interval, dtype=nu.dtype, device=nu.device).reshape(-1, 1)
    C = torch.diagonal(S, dim1=-2, dim2=-1).clamp_min(0)
    horizontal = torch.linalg.vector_norm(nu[..., :2], dim=-1) <= 0.5 * rule.accel * dt**2 + 3.0 * C[..., :2].sum(-1).sqrt()
    vertical = nu[..., 2].abs() <= 0.5 * rule.vertical_accel * dt**2 + 3.0 * C[..., 2].sqrt()
    return (horizontal & vertical).any(-1)


def advance(rule: Reacquire, state: Watch, z: torch.Tensor, R: torch.Tensor, interval, maha: torch.Tensor,
            active: torch.Tensor | None = None, reach: torch.Tensor | None = None) -> tuple[Watch, torch.Tensor, torch.Tensor]:
    """One scan of re-acquisition for every track: the watch after it, the tracks that restart at it ``[B]`` (bool) and
    those whose detection the filters do not take (far, not restarting, with ``reject``; ``[B]`` bool).

    ``z [B, 3]`` the scan's detections (NaN: missed), ``R [B, 3, 3]`` their covariances (read where detected),
    ``interval`` the time since the previous scan (a number or ``[B]``, s), ``maha [B, M]`` each filter's squared
    Mahalanobis distance of the detection (``nu^T S^-1 nu`` of ``innovations``; read where detected), ``active [B]``
    the tracks that started before this scan (None: all; the others' watch is left as it is), ``reach [B]`` the tracks
    whose detection is within the target's reach (``reachable``: a far one is still far, and not rejected).

    Two detections agree where the second lies within ``speed`` times the time between them of the first horizontally
    and within ``climb`` times it vertically, each to three standard deviations of their noise there (``sqrt`` of the
    horizontal trace of ``R_1 + R_2``, of its vertical variance). A starting track's next detection that disagrees
    with its first restarts it there (the first was an outlier, or this one is and the next restarts it again); one
    that agrees confirms the start. A confirmed track's detection beyond ``gate`` of every filter is far: ``scans``
    consecutive far detections, each agreeing with the one before (missed scans between them count as time), restart
    the track at the last; a detection inside some filter's gate ends the run. A restarted track starts anew there."""
    count, plot, cov, elapsed = state
    detected = torch.isfinite(z).all(-1)
    if active is not None:
        detected = detected & active
    iv = torch.as_tensor(interval, dtype=elapsed.dtype, device=elapsed.device)
    since = elapsed + iv if active is None else torch.where(active, elapsed + iv, elapsed)
    zc, Rc = torch.nan_to_num(z), torch.nan_to_num(R)
    gap = zc - plot
    var = torch.diagonal(Rc + cov, dim1=-2, dim2=-1).clamp_min(0)  # [B, 3]
    horizontal = torch.linalg.vector_norm(gap[:, :2], dim=-1) <= rule.speed * since + 3.0 * var[:, :2].sum(-1).sqrt()
    vertical = gap[:, 2].abs() <= rule.climb * since + 3.0 * var[:, 2].sqrt()
    agrees = horizontal & vertical
    starting = count < 0
    far = detected & ~starting & (torch.nan_to_num(maha, nan=math.inf).amin(-1) > rule.gate)
    run = torch.where(far & (count > 0) & agrees, count + 1, torch.ones_like(count))
    count = torch.where(far, run, torch.where(detected, torch.zeros_like(count), count))
    restart = (far & (count >= rule.scans)) | (detected & starting & ~agrees)
    mark = far | restart  # the plot watched from here on: the run's last, or the new start's
    new = Watch(torch.where(restart, torch.full_like(count, -1.0), count),
                torch.where(mark[:, None], zc, plot),
                torch.where(mark[:, None, None], Rc.to(cov.dtype), cov),
                torch.where(mark, torch.zeros_like(since), since))
    rejected = far & ~restart if reach is None else far & ~restart & ~reach
    return new, restart, rejected if rule.reject else torch.zeros_like(far)


def per_track_cov(R, batch: int, like: torch.Tensor) -> torch.Tensor:
    """A scan's measurement variance or covariance as the scan loop holds it (a number, ``[B]``, ``[B, 1]``, ``[3, 3]``,
    ``[B, 1, 3, 3]`` or ``[B, 3, 3]``) as one covariance per track ``[B, 3, 3]``."""
    R = torch.as_tensor(R, dtype=like.dtype, device=like.device)
    if R.dim() < 2 or R.shape[-2:] != (3, 3):
        R = _as_cov(R.reshape(-1), 3, like)
    return R.reshape(-1, 3, 3).expand(batch, 3, 3)


class Restarts:
    """Re-acquisition in the model-based scan loop (``immnet.imm.runner.run(reacquire=...)``): the ``rule``, the
    interval before each scan ``intervals`` (a number, or ``[B, T]``), the start's velocity and acceleration stds
    (``immnet.filters.imm``'s ``VEL_STD``, ``ACC_STD``), the filters' prior mode probabilities ``mu0 [M]`` and the
    start's prior on the vertical speed ``vz_std`` (``start_state``)."""

    def __init__(self, rule: Reacquire, intervals, vel_std: float, acc_std: float, mu0: torch.Tensor,
                 vz_std: float | None = None):
        self.rule, self.intervals, self.vel_std, self.acc_std, self.mu0 = rule, intervals, vel_std, acc_std, mu0
        self.vz_std = vz_std

    def begin(self, x: torch.Tensor, P: torch.Tensor) -> Watch:
        """The watch of tracks that start at the filters' states ``x [B, M, 9]``, ``P`` (their first detection's
        position and covariance)."""
        return started(x[:, 0, 0::3], P[:, 0, 0::3, 0::3])

    def observe(self, state: Watch, t: int, z: torch.Tensor, R, xp, Pp, start=None):
        """Scan ``t``'s re-acquisition before the update: ``z [B, 3]``, ``R`` its measurement noise as the loop holds
        it, the filters' predictions ``xp [B, M, 9]``, ``Pp``; ``start [B]`` each track's first scan (None: 0). Returns
        ``(state, z, restart)``: the watch after it, the detections the update takes (NaN where rejected) and the
        tracks that restart here (``restart``)."""
        Rb = per_track_cov(R, z.shape[0], z)
        iv = self.intervals[:, t] if isinstance(self.intervals, torch.Tensor) and self.intervals.dim() == 2 else self.intervals
        active = None if start is None else t > start.to(z.device)
        nu, S = innovations(torch.nan_to_num(z), xp, Pp, Rb)
        state, restart, rejected = advance(self.rule, state, z, Rb, iv, quadratic(inv3(S)[0], nu), active,
                                           reachable(self.rule, nu, S, iv))
        return state, torch.where(rejected[:, None], torch.full_like(z, float("nan")), z), restart

    def restart(self, restart: torch.Tensor, z: torch.Tensor, R, x, P, mu):
        """The filters ``x [B, M, 9]``, ``P`` and mode probabilities ``mu [B, M]`` after the update, the tracks of
        ``restart [B]`` at their detection ``z [B, 3]`` (``start_state``, its covariance ``R``) with ``mu0``."""
        if not bool(restart.any()):  # one host read per scan, with re-acquisition on
            return x, P, mu
        x1, P1 = start_state(torch.nan_to_num(z), per_track_cov(R, z.shape[0], z), self.vel_std, self.acc_std,
                             self.vz_std)
        again = restart[:, None]
        x = torch.where(again[..., None], x1[:, None].to(x.dtype), x)
        P = torch.where(again[..., None, None], P1[:, None].to(P.dtype), P)
        mu = torch.where(again, self.mu0.to(mu).expand_as(mu), mu)
        return x, P, mu
