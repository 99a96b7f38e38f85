"""A simulated radar over real flights: site, coverage, scan times, measurement noise (docs/data.md).

The radar sits at a site ``(lat0, lon0, h0)``; positions are its local east-north-up coordinates
(:mod:`immnet.data.geodesy`). It sees a point within ``max_range`` (slant range, m) above its horizon
(elevation >= ``min_elevation``). It scans at ``t_k = t_0 + sum dt_j``, ``dt_j = dt`` or
``dt_j ~ U[dt - jitter, dt + jitter]``, and measures as 3D-LAST does: ``z = p + v``, ``v ~ N(0, r^2 I3)``,
``r`` one level per window; a scan after the second is missed (NaN) with probability ``p_miss``.

Polar measurements (range ``rho``, azimuth ``az`` clockwise from north, elevation ``el``) convert to ENU as
``e = rho cos el sin az``, ``n = rho cos el cos az``, ``u = rho sin el``; the converted measurement's
covariance to first order is ``J diag(s_rho^2, s_az^2, s_el^2) J^T`` with ``J`` the Jacobian of that map
(:func:`polar_covariance`; exact to O(s_angle^2) relative, e.g. 1 mrad at 100 km).
"""

from __future__ import annotations

import numpy as np


def median_site(lat: np.ndarray, lon: np.ndarray) -> tuple[float, float, float]:
    """The default site: the median latitude and longitude of the positions, at height 0."""
    return float(np.median(lat)), float(np.median(lon)), 0.0


def polar(enu) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ENU ``[..., 3]`` -> slant range (m), azimuth (rad, clockwise from north, [0, 2 pi)), elevation (rad)."""
    enu = np.asarray(enu, np.float64)
    e, n, u = enu[..., 0], enu[..., 1], enu[..., 2]
    ground = np.hypot(e, n)
    return np.sqrt(ground * ground + u * u), np.mod(np.arctan2(e, n), 2 * np.pi), np.arctan2(u, ground)


def from_polar(rho, az, el) -> np.ndarray:
    """Slant range, azimuth, elevation -> ENU ``[..., 3]`` (m)."""
    rho, az, el = (np.asarray(a, np.float64) for a in (rho, az, el))
    c = rho * np.cos(el)
    return np.stack([c * np.sin(az), c * np.cos(az), rho * np.sin(el)], -1)


def polar_covariance(rho, az, el, s_rho, s_az, s_el) -> np.ndarray:
    """The first-order covariance ``[..., 3, 3]`` of :func:`from_polar` under independent Gaussian noise of
    standard deviations ``s_rho`` (m), ``s_az``, ``s_el`` (rad): ``J diag(s^2) J^T``."""
    rho, az, el = (np.asarray(a, np.float64) for a in (rho, az, el))
    ca, sa, ce, se = np.cos(az), np.sin(az), np.cos(el), np.sin(el)
    J = np.stack([
        np.stack([ce * sa, rho * ce * ca, -rho * se * sa], -1),
        np.stack([ce * ca, -rho * ce * sa, -rho * se * ca], -1),
        np.stack([se, np.zeros_like(se), rho * ce], -1),
    ], -2)
    s2 = np.stack(np.broadcast_arrays(*(np.asarray(s, np.float64) ** 2 for s in (s_rho, s_az, s_el))), -1)
    return (J * s2[..., None, :]) @ np.swapaxes(J, -1, -2)


def covered(enu, max_range: float, min_elevation: float = 0.0) -> np.ndarray:
    """Where the radar sees a point: slant range <= ``max_range`` (m), elevation >= ``min_elevation`` (degrees)."""
    rho, _, el = polar(enu)
    return (rho <= max_range) & (el >= np.radians(min_elevation))


def scan_times(t0: float, t1: float, dt: float, jitter: float, rng: np.random.Generator) -> np.ndarray:
    """Scan times from ``t0 + u dt`` (``u ~ U[0, 1)``) up to ``t1``: a fixed ``dt`` or intervals
    ``U[dt - jitter, dt + jitter]`` (``0 <= jitter < dt``)."""
    if not (dt > 0 and 0 <= jitter < dt):
        raise ValueError(f"the scan interval needs dt > 0 and 0 <= jitter < dt, got dt={dt}, jitter={jitter}")
    start = t0 + rng.uniform(0.0, dt)
    n = max(int(np.floor((t1 - start) / max(dt - jitter, 1e-9))) + 1, 1)
    if jitter == 0:
        t = start + dt * np.arange(n)
    else:
        t = start + np.r_[0.0, np.cumsum(rng.uniform(dt - jitter, dt + jitter, n - 1))]
    return t[t <= t1]


def measure(pos: np.ndarray, r: float, p_miss: float, rng: np.random.Generator) -> np.ndarray:
    """Measurements ``[T, 3]`` of true positions ``pos [T, 3]``: ``pos + r N(0, I3)``, scans after the
    second missed (NaN) with probability ``p_miss``."""
    z = pos + r * rng.standard_normal(pos.shape)
    if p_miss > 0:
        miss = rng.random(len(pos)) < p_miss
        miss[:2] = False
        z[miss] = np.nan
    return z
