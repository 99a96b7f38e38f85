"""Measurement models as a role: what a model-based filter's update takes a detection's error to be (docs/tracking.md,
"Measurement models").

Positions are the radar's east-north-up frame (x east, y north, z up, metres, origin at the radar); a polar plot is
slant range ``rho``, azimuth ``az`` clockwise from north and elevation ``el`` above the horizontal
(``immnet.data.radar``, which this module does not import: the IMM core knows no data set). One class per kind, each a
small frozen dataclass, written in a configuration's ``r`` as in brackets (:func:`measurement_model` reads it):

- ``Isotropic(r)`` (a number): ``z = H x + v``, ``v ~ N(0, r^2 I)``, one ``r`` (m) for every track, and ``ToldStd()``
  (``"data"``), each track's own, the batch's ``r [B]``: the models every tracker here was built on;
- ``PerDetection()`` (``"detection"``): ``v ~ N(0, R_t)``, each detection's own covariance, the batch's ``meas_cov
  [B, T, 3, 3]`` (``immnet.keys.MEAS_COV``; a polar plot's :func:`immnet.data.radar.converted` covariance, or any's);
- ``Polar(sigma_range, sigma_azimuth, sigma_elevation)`` (``{sigma_range, sigma_azimuth_deg, sigma_elevation_deg}``):
  the plot itself, ``h(x) = (rho, az, el)`` of the position rows (0, 3, 6) of the 9-D state ``[x, vx, ax, y, vy, ay,
  z, vz, az]``, with independent Gaussian errors of those standard deviations (m, rad, rad; numbers, one radar, or
  tensors ``[B, T]``, one per detection), updated by the extended Kalman filter (:func:`polar_update`);
- ``Estimated()`` (None): each track's ``r`` estimated from its own measurements, by IMMNet's filter experts alone.

Each says what of the batch it ``needs`` and gives what an update needs: the first two a std (``std``),
``PerDetection`` a covariance for ``immnet.imm.kalman.update`` (``R``), ``Polar`` its update (``measure``, for
``immnet.imm.runner.run``) and a track's start covariance (``initial_cov``); a filter branches on the model's kind,
never on its spelling. A ``Polar`` model reads a batch's measurements as the conversion of its plots
(``immnet.data.radar.from_polar``: the plain conversion is inverted exactly; an unbiased converted measurement
differs from it by ``rho s^2 / 2``, under a tenth of the range error at the issue's stds).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from tensordict import TensorDict

from immnet import keys
from immnet.imm.kalman import innovation_update, narrow, wide_dtype
from immnet.imm.option import is_number, positive

TOLD, DETECTION = "data", "detection"  # a configuration's spellings of ToldStd and PerDetection (r: data, detection)


@dataclass(frozen=True)
class Isotropic:
    """``R = r^2 I``, one ``r`` (m) for every track (configured as a number)."""

    r: float
    needs = ()
    spelling = "a positive number"

    def __post_init__(self):
        positive(self.r, "Isotropic.r must be a positive number")

    def std(self, batch: TensorDict, dtype, device) -> float:
        return float(self.r)


@dataclass(frozen=True)
class ToldStd:
    """``R = r^2 I`` with each track's own ``r``, the batch's ``r [B]`` (configured as ``"data"``: a radar that knows
    its accuracy; IMMNet's filter experts: the step's input ``"r"``)."""

    needs = (keys.R,)
    spelling = f"{TOLD!r} (each track's own r)"

    def std(self, batch: TensorDict, dtype, device) -> torch.Tensor:
        return batch[keys.R].to(dtype=dtype, device=device).reshape(-1)


@dataclass(frozen=True)
class Estimated:
    """Each track's ``r`` estimated from its own measurements (configured as None): IMMNet's filter experts alone
    (``FilterGain``: the running mean of the altitude's third differences)."""

    needs = ()
    spelling = "None (estimated per track)"


@dataclass(frozen=True)
class PerDetection:
    """Each detection's own covariance, the batch's ``meas_cov [B, T, 3, 3]`` (m^2, ENU; NaN where missed)."""

    needs = (keys.MEAS_COV,)
    spelling = f"{DETECTION!r} (each detection's covariance, {keys.MEAS_COV!r})"

    def R(self, batch: TensorDict, dtype, device) -> torch.Tensor:
        """``[B, T, 3, 3]``, checked: finite and symmetric with positive pivots at every detection (a ValueError in
        one line naming the first that is not); the identity where a scan is missed (no update reads it)."""
        z = batch[keys.MEASUREMENTS]
        R = batch[keys.MEAS_COV]
        if R.shape != (*z.shape[:2], 3, 3):
            raise ValueError(f"{keys.MEAS_COV!r} must be [B, T, 3, 3] beside measurements {list(z.shape)}, "
                             f"got {list(R.shape)}")
        R = R.to(dtype=dtype, device=device)
        detected = ~torch.isnan(z.to(device)).any(-1)
        bad = detected & ~torch.isfinite(R).flatten(-2).all(-1)
        if not bad.any():
            a, b, c = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
            sym = (R - R.transpose(-1, -2)).abs().flatten(-2).amax(-1) <= 1e-6 * torch.maximum(torch.maximum(a, b), c).abs()
            det = torch.linalg.det(R.double().nan_to_num(0.0))
            m2 = a * b - R[..., 0, 1] * R[..., 1, 0]
            bad = detected & ~(sym & (a > 0) & (m2 > 0) & (det > 0))
        if bad.any():
            b, t = (int(v) for v in bad.nonzero()[0])
            raise ValueError(f"{keys.MEAS_COV!r} of track {b}, scan {t} is not a finite symmetric positive-definite "
                             f"3x3 covariance: {R[b, t].tolist()}")
        eye = torch.eye(3, dtype=dtype, device=device)
        return torch.where(detected[..., None, None], R, eye)


@dataclass(frozen=True)
class Polar:
    """A plot's slant range, azimuth and elevation with independent Gaussian errors of standard deviations
    ``sigma_range`` (m), ``sigma_azimuth``, ``sigma_elevation`` (rad): numbers (one radar) or tensors broadcastable to
    ``[B, T]`` (one per detection). ``from_config`` takes degrees (``sigma_azimuth_deg``, ``sigma_elevation_deg``)."""

    sigma_range: float | torch.Tensor
    sigma_azimuth: float | torch.Tensor
    sigma_elevation: float | torch.Tensor

    needs = ()
    spelling = "a polar model {sigma_range, sigma_azimuth_deg, sigma_elevation_deg}"

    def __post_init__(self):  # each standard deviation a positive number or a tensor of them
        for name in ("sigma_range", "sigma_azimuth", "sigma_elevation"):
            value = getattr(self, name)
            if not isinstance(value, torch.Tensor):
                positive(value, f"Polar.{name} must be a positive number (or a tensor of them)")
            elif not (torch.isfinite(value).all() and (value > 0).all()):
                raise ValueError(f"Polar.{name} must be finite and > 0 everywhere")

    @classmethod
    def from_config(cls, config: dict) -> "Polar":
        known = {"sigma_range", "sigma_azimuth_deg", "sigma_elevation_deg"}
        if not isinstance(config, dict) or set(config) != known:
            raise ValueError(f"a polar measurement model takes exactly {sorted(known)}, got {config!r}")
        return cls(float(config["sigma_range"]), math.radians(config["sigma_azimuth_deg"]),
                   math.radians(config["sigma_elevation_deg"]))

    def sigmas(self, shape, dtype, device) -> torch.Tensor:
        """The three standard deviations of every detection, ``[*shape, 3]`` (``shape`` ``(B, T)``)."""
        return torch.stack([torch.as_tensor(s, dtype=dtype, device=device).expand(shape)
                            for s in (self.sigma_range, self.sigma_azimuth, self.sigma_elevation)], -1)

    def initial_cov(self, z0: torch.Tensor, sig0: torch.Tensor) -> torch.Tensor:
        """The first detection's Cartesian covariance ``[B, 3, 3]`` to first order, ``J diag(sigma^2) J^T`` with ``J``
        the Jacobian of the conversion at the plot of ``z0 [B, 3]`` (``immnet.data.radar.polar_covariance``'s; a
        track with no detection, its NaN row, gets ``sigma_range^2 I``)."""
        rho, az, el = to_polar(z0).unbind(-1)
        ca, sa, ce, se = az.cos(), az.sin(), el.cos(), el.sin()
        J = torch.stack([
            torch.stack([ce * sa, rho * ce * ca, -rho * se * sa], -1),
            torch.stack([ce * ca, -rho * ce * sa, -rho * se * ca], -1),
            torch.stack([se, torch.zeros_like(se), rho * ce], -1),
        ], -2)
        R = (J * (sig0 * sig0).unsqueeze(-2)) @ J.transpose(-1, -2)
        fallback = sig0[:, :1, None] ** 2 * torch.eye(3, dtype=z0.dtype, device=z0.device)
        return torch.where(torch.isfinite(R).all(-1).all(-1)[:, None, None], R, fallback)

    def measure(self, z: torch.Tensor, robust: float | None = None) -> Callable:
        """``run``'s ``measure(t, xp, Pp, spare)`` over ENU measurements ``z [B, T, 3]``: :func:`polar_update` of each filter
        ``[B, M, ...]`` with scan ``t``'s plot."""
        plots = to_polar(z)  # the plots (rho, az, el); NaN stays NaN
        sig = self.sigmas(z.shape[:2], z.dtype, z.device)

        def measure(t: int, xp: torch.Tensor, Pp: torch.Tensor, spare: torch.Tensor | None = None):
            return polar_update(xp, Pp, plots[:, t, None], sig[:, t, None], robust=robust, spare=spare)

        return measure


def to_polar(z: torch.Tensor) -> torch.Tensor:
    """ENU ``[..., 3]`` -> ``(rho, az, el)``: azimuth clockwise from north in ``[0, 2 pi)``, elevation above the
    horizontal (``immnet.data.radar.polar`` in torch)."""
    e, n, u = z[..., 0], z[..., 1], z[..., 2]
    ground = torch.hypot(e, n)
    return torch.stack([torch.sqrt(ground * ground + u * u), torch.remainder(torch.atan2(e, n), 2 * math.pi),
                        torch.atan2(u, ground)], -1)


def wrap(angle: torch.Tensor) -> torch.Tensor:
    """An angle difference in ``(-pi, pi]``."""
    return math.pi - torch.remainder(math.pi - angle, 2 * math.pi)


def polar_jacobian(pos: torch.Tensor) -> torch.Tensor:
    """``d(rho, az, el) / d(e, n, u)`` ``[..., 3, 3]`` at positions ``pos [..., 3]`` (``az = atan2(e, n)``,
    ``el = atan2(u, sqrt(e^2 + n^2))``)."""
    e, n, u = pos[..., 0], pos[..., 1], pos[..., 2]
    g2 = e * e + n * n
    g = torch.sqrt(g2)
    r2 = g2 + u * u
    rho = torch.sqrt(r2)
    zero = torch.zeros_like(e)
    return torch.stack([
        torch.stack([e / rho, n / rho, u / rho], -1),
        torch.stack([n / g2, -e / g2, zero], -1),
        torch.stack([-u * e / (r2 * g), -u * n / (r2 * g), g / r2], -1),
    ], -2)


def polar_update(x: torch.Tensor, P: torch.Tensor, plot: torch.Tensor, sigma: torch.Tensor,
                 robust: float | None = None, spare: torch.Tensor | None = None):
    """The extended Kalman filter's update with a polar plot; returns ``(x_post, P_post, loglik)`` (and ``far`` with
    ``spare``: ``kalman.innovation_update``).

    ``x [..., 9]``, ``P [..., 9, 9]`` (positions at rows 0, 3, 6), ``plot [..., 3]`` = ``(rho, az, el)`` (NaN anywhere:
    missed, the prior kept and ``loglik`` 0), ``sigma [..., 3]`` its standard deviations (m, rad, rad)::

        nu = plot - h(x),  nu_az wrapped to (-pi, pi]      H = dh/dx at x (polar_jacobian on the position columns)
        S = H P H^T + diag(sigma^2)   K = P H^T S^-1       x_post = x + K nu
        P_post = (I - K H) P (I - K H)^T + K R K^T  (Joseph's form, expanded as P - K H P - (K H P)^T + K S K^T)
        loglik = log N(nu; 0, S)

    The wrapped azimuth innovation keeps a target crossing north (359.9 -> 0.1 deg) a 0.2 deg step. ``robust``:
    Huber's ``k`` (``immnet.imm.kalman``'s module doc: ``K -> w K``, ``S -> S / w``). A float32 input is updated in
    float64 (``kalman.wide_dtype``) and rounded back; the update is ``kalman.innovation_update``'s.
    """
    dtype = x.dtype
    wide = wide_dtype(dtype, x.device)
    x, P, plot, sigma = (v.to(wide) for v in (x, P, plot, sigma))
    missed = torch.isnan(plot).any(-1)
    pos = x[..., 0::3]
    J = polar_jacobian(pos)  # [..., 3, 3]
    nu = torch.where(missed[..., None], torch.zeros_like(plot), plot - to_polar(pos))
    nu = torch.cat([nu[..., :1], wrap(nu[..., 1:2]), nu[..., 2:]], -1)
    HP = J @ P[..., 0::3, :]  # [..., 3, 9]
    S = HP[..., 0::3] @ J.transpose(-1, -2) + torch.diag_embed(sigma * sigma)
    return narrow(innovation_update(x, P, nu, HP, S, missed, robust, spare), dtype)


KINDS = (Isotropic, ToldStd, PerDetection, Polar, Estimated)  # every measurement model's kind
MODEL_BASED = KINDS[:4]  # the kinds a model-based tracker takes: all but Estimated (IMMNet's filter experts alone)


def measurement_model(r, takes: tuple[type, ...] = MODEL_BASED):
    """A configuration's ``r`` as its measurement model, one of ``takes`` (the kinds the caller filters with; a
    model-based tracker's by default): a positive number (``Isotropic``), ``"data"`` (``ToldStd``), ``"detection"``
    (``PerDetection``), a dict ``{sigma_range, sigma_azimuth_deg, sigma_elevation_deg}`` (``Polar.from_config``),
    None (``Estimated``) or a model itself; anything else, or a kind not in ``takes``, a ValueError in one
    line naming what ``takes`` takes."""
    model = r
    if isinstance(r, dict):
        model = Polar.from_config(r)
    elif r is None:
        model = Estimated()
    elif isinstance(r, str):
        model = {TOLD: ToldStd(), DETECTION: PerDetection()}.get(r, r)
    elif is_number(r) and r > 0:
        model = Isotropic(float(r))
    if not isinstance(model, takes):
        kinds = [kind.spelling for kind in takes]
        options = kinds[0] if len(kinds) == 1 else f"{', '.join(kinds[:-1])} or {kinds[-1]}"
        kind = f" ({type(model).__name__}, which this filter does not take)" if isinstance(model, KINDS) else ""
        raise ValueError(f"r must be {options}, got {r!r}{kind}")
    return model
