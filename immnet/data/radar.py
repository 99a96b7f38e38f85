"""A simulated radar over real flights: site, coverage, scan times, measurement noise (docs/data.md).

The radar sits at a site ``(lat0, lon0, h0)``; positions are its local east-north-up coordinates
(:mod:`immnet.data.geodesy`). It sees a point within ``max_range`` (slant range, m) above its horizon
(elevation >= ``min_elevation``). It scans at ``t_k = t_0 + sum dt_j``, ``dt_j = dt`` or
``dt_j ~ U[dt - jitter, dt + jitter]``, and measures as 3D-LAST does: ``z = p + v``, ``v ~ N(0, r^2 I3)``,
``r`` one level per window; a scan after the second is missed (NaN) with probability ``p_miss``.

Polar measurements (range ``rho``, azimuth ``az`` clockwise from north, elevation ``el``) convert to ENU as
``e = rho cos el sin az``, ``n = rho cos el cos az``, ``u = rho sin el``; the converted measurement's
covariance to first order is ``J diag(s_rho^2, s_az^2, s_el^2) J^T`` with ``J`` the Jacobian of that map
(:func:`polar_covariance`; exact to O(s_angle^2) relative, e.g. 1 mrad at 100 km). That plain conversion is biased
(``E[cos(az + v)] = cos(az) e^{-s_az^2/2}``): :func:`converted` gives the unbiased converted measurement and its
covariance, the input of every tracker that filters Cartesian positions (docs/tracking.md "Measurement models").
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


def _ucm_cov(A, Bq, az, el, s_az, s_el, g1a, g2a, g2e):
    """The covariance ``[..., 3, 3]`` of the unbiased conversion (:func:`converted`'s formula) from its moments: ``A``
    the expected ``rho_m^2``, ``Bq`` the expected ``rho^2`` and ``g1a``, ``g2a``, ``g2e`` the factors that take
    ``sin az``, ``sin/cos 2 az`` and ``sin/cos 2 el`` to their expectations."""
    la2, le2 = np.exp(-s_az * s_az), np.exp(-s_el * s_el)  # lambda_az^2, lambda_el^2
    la4, le4 = la2 * la2, le2 * le2
    c2a, s2a, c2e, s2e = np.cos(2 * az), np.sin(2 * az), np.cos(2 * el), np.sin(2 * el)
    horizontal = A / (la2 * le2) * 0.25 * (1 + le4 * g2e * c2e)
    ground = Bq * 0.25 * (1 + g2e * c2e)
    xx = horizontal * (1 - la4 * g2a * c2a) - ground * (1 - g2a * c2a)
    yy = horizontal * (1 + la4 * g2a * c2a) - ground * (1 + g2a * c2a)
    xy = horizontal * la4 * g2a * s2a - ground * g2a * s2a
    zz = A / le2 * 0.5 * (1 - le4 * g2e * c2e) - Bq * 0.5 * (1 - g2e * c2e)
    vertical = 0.5 * g2e * s2e * g1a * (A * le2 - Bq)
    xz, yz = vertical * np.sin(az), vertical * np.cos(az)
    return np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)], -2)


def converted(rho, az, el, s_rho, s_az, s_el, given: str = "measurement") -> tuple[np.ndarray, np.ndarray]:
    """The unbiased converted measurement of a polar plot and its covariance (float64): ``(enu [..., 3], R [..., 3, 3])``.

    ``rho`` (m), ``az`` (rad, clockwise from north), ``el`` (rad, above the horizontal) measured with independent
    Gaussian errors of standard deviations ``s_rho`` (m), ``s_az``, ``s_el`` (rad); all broadcast together. With
    ``lambda_a = e^{-s_az^2/2}``, ``lambda_e = e^{-s_el^2/2}`` (``E[cos v] = lambda`` for ``v ~ N(0, s^2)``), the
    conversion divides the plain one (:func:`from_polar`) by what its expectation multiplies the truth by::

        e = rho cos(el) sin(az) / (lambda_a lambda_e)
        n = rho cos(el) cos(az) / (lambda_a lambda_e)
        u = rho sin(el) / lambda_e

    so that ``E[enu | truth] = truth`` at any range and noise (Mo, Song, Zhou, Sun and Bar-Shalom, "Unbiased
    converted measurements for tracking", IEEE TAES 1998, in this frame).

    ``R`` is the covariance of that error given the truth, ``C(truth) = Cov(enu | rho, az, el)``, averaged over the
    truths the measurement could have come from (``truth = measured - v``), ``E[C | measured]`` (Duan, Han and Li's
    correction, IEEE TAES 2004: ``C`` evaluated at the measured values is biased itself). With ``A = rho^2 + 2
    s_rho^2``, ``Bq = rho^2 + s_rho^2`` (``E[rho_m^2 | truth]`` and ``E[rho^2 | measured]``), ``g1a = lambda_a``,
    ``g2a = lambda_a^4``, ``g2e = lambda_e^4`` (``E[sin(az - v)] = lambda_a sin az``, ``E[cos 2(az - v)] = lambda_a^4
    cos 2 az``), and ``ce2 = 1 + lambda_e^4 g2e cos 2el``::

        R_ee = A/(la^2 le^2) ce2 (1 - la^4 g2a cos 2az)/4 - Bq (1 + g2e cos 2el)(1 - g2a cos 2az)/4
        R_nn = A/(la^2 le^2) ce2 (1 + la^4 g2a cos 2az)/4 - Bq (1 + g2e cos 2el)(1 + g2a cos 2az)/4
        R_en = A/(la^2 le^2) ce2 la^4 g2a sin 2az / 4   - Bq (1 + g2e cos 2el) g2a sin 2az / 4
        R_uu = A/le^2 (1 - le^4 g2e cos 2el)/2          - Bq (1 - g2e cos 2el)/2
        R_eu = g2e sin 2el g1a sin az (A le^2 - Bq)/2    R_nu = the same with cos az

    (``la``, ``le`` the lambdas; each line ``E[(enu)(enu)^T]`` less the truth's outer product). ``given="truth"``
    reads ``(rho, az, el)`` as the truth and returns ``C(truth)`` itself (``A = rho^2 + s_rho^2``, ``Bq = rho^2``,
    ``g1a = g2a = g2e = 1``): the covariance a Monte Carlo of the conversion at that truth measures. To first order
    in the noise both are :func:`polar_covariance`'s ``J diag(s^2) J^T``.
    """
    rho, az, el, s_rho, s_az, s_el = (np.asarray(a, np.float64) for a in (rho, az, el, s_rho, s_az, s_el))
    la, le = np.exp(-0.5 * s_az * s_az), np.exp(-0.5 * s_el * s_el)
    c = rho * np.cos(el) / (la * le)
    enu = np.stack(np.broadcast_arrays(c * np.sin(az), c * np.cos(az), rho * np.sin(el) / le), -1)
    if given == "measurement":
        A, Bq, g1a, g2a, g2e = rho * rho + 2 * s_rho * s_rho, rho * rho + s_rho * s_rho, la, la**4, le**4
    elif given == "truth":
        A, Bq, g1a, g2a, g2e = rho * rho + s_rho * s_rho, rho * rho, 1.0, 1.0, 1.0
    else:
        raise ValueError(f"given must be 'measurement' or 'truth', got {given!r}")
    return enu, _ucm_cov(A, Bq, az, el, s_az, s_el, g1a, g2a, g2e)


def check_plot_settings(given: list[str], outliers: float, outlier_scale: float) -> None:
    """A radar's plot settings as real flights' and 3D-LAST's data take them: the stds ``given`` (their names) all three
    or none, the outliers' share in [0, 1) and their scale >= 1; a ValueError naming what is wrong."""
    if given and len(given) < 3:
        raise ValueError(f"a radar's plots need sigma_range, sigma_azimuth and sigma_elevation together, got "
                         f"{', '.join(given)} alone")
    if not 0 <= outliers < 1 or not outlier_scale >= 1:
        raise ValueError(f"outliers is a share in [0, 1) and outlier_scale >= 1, got {outliers:g}, {outlier_scale:g}")


def covered(enu, max_range: float, min_elevation: float = 0.0) -> np.ndarray:
    """Where the radar sees a point: slant range <= ``max_range`` (m), elevation >= ``min_elevation`` (degrees)."""
    rho, _, el = polar(enu)
    return (rho <= max_range) & (el >= np.radians(min_elevation))


def check_scan_interval(dt: float, dt_jitter: float) -> None:
    """A ValueError unless ``dt > 0`` and ``0 <= dt_jitter < dt``, so that every scan interval ``U[dt - dt_jitter,
    dt + dt_jitter]`` is > 0: the one check of ``DataSpec``, ``RealSpec``, ``SceneSpec`` and :func:`scan_times`."""
    if not (dt > 0 and 0 <= dt_jitter < dt):
        raise ValueError(f"the scan interval needs dt > 0 and 0 <= dt_jitter < dt, got dt={dt}, dt_jitter={dt_jitter}")


def scan_times(t0: float, t1: float, dt: float, jitter: float, rng: np.random.Generator) -> np.ndarray:
    """Scan times from ``t0 + u dt`` (``u ~ U[0, 1)``) up to ``t1``: a fixed ``dt`` or intervals
    ``U[dt - jitter, dt + jitter]`` (``0 <= jitter < dt``)."""
    check_scan_interval(dt, jitter)
    start = t0 + rng.uniform(0.0, dt)
    n = max(int(np.floor((t1 - start) / max(dt - jitter, 1e-9))) + 1, 1)
    if jitter == 0:
        t = start + dt * np.arange(n)
    else:
        t = start + np.r_[0.0, np.cumsum(rng.uniform(dt - jitter, dt + jitter, n - 1))]
    return t[t <= t1]


def _missed(shape: tuple, p_miss: float, rng: np.random.Generator) -> np.ndarray:
    """Which scans ``shape`` (scans on the last axis) are missed: each after the second with probability ``p_miss``
    (drawn only where it is > 0)."""
    miss = np.zeros(shape, bool)
    if p_miss > 0:
        miss = rng.random(shape) < p_miss
        miss[..., :2] = False
    return miss


def measure(pos: np.ndarray, r: float, p_miss: float, rng: np.random.Generator) -> np.ndarray:
    """Measurements ``[T, 3]`` of true positions ``pos [T, 3]``: ``pos + r N(0, I3)``, scans after the
    second missed (NaN) with probability ``p_miss``."""
    z = pos + r * rng.standard_normal(pos.shape)
    z[_missed(pos.shape[:-1], p_miss, rng)] = np.nan
    return z


def plots(pos: np.ndarray, sigma_range, sigma_azimuth, sigma_elevation, p_miss: float, outliers: float,
          outlier_scale: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A radar's plots of true positions ``pos [..., T, 3]`` (ENU about the radar, m), one window per leading
    index: stds drawn per window, ``U[LOW, HIGH]`` of each pair ``sigma_range`` (m), ``sigma_azimuth``,
    ``sigma_elevation`` (degrees); slant range, azimuth and elevation each measured with its own Gaussian noise; scans
    after the second missed with probability ``p_miss``; converted to east-north-up with each plot's covariance
    (the unbiased converted measurement, :func:`converted`). The noise only, not the plot's stated covariance, of a
    share ``outliers`` of the detections is ``outlier_scale`` times larger.

    Returns ``(z [..., T, 3], r [...], cov [..., T, 3, 3])`` (NaN where missed), ``r`` the RMS of the per-axis stds
    of each window's covariances. Draws, in order: the three stds, the noise, the misses (only with ``p_miss > 0``),
    the outliers (only with ``outliers > 0``)."""
    pos = np.asarray(pos, np.float64)
    batch = pos.shape[:-2]
    s = np.stack([rng.uniform(*sigma_range, size=batch), np.radians(rng.uniform(*sigma_azimuth, size=batch)),
                  np.radians(rng.uniform(*sigma_elevation, size=batch))], -1)
    noise = rng.standard_normal(pos.shape) * s[..., None, :]
    miss = _missed(pos.shape[:-1], p_miss, rng)
    if outliers > 0:
        noise[rng.random(pos.shape[:-1]) < outliers] *= outlier_scale
    rho, az, el = polar(pos)
    stds = s[..., None, :] if batch else s  # one window: scalars (numpy rounds scalar exp, sin a bit unlike arrays)
    z, cov = converted(rho + noise[..., 0], np.mod(az + noise[..., 1], 2 * np.pi), el + noise[..., 2],
                       *(stds[..., i] for i in range(3)))
    z[miss], cov[miss] = np.nan, np.nan
    var = np.trace(cov, axis1=-2, axis2=-1).reshape(-1, pos.shape[-2]) / 3
    seen = ~miss.reshape(var.shape)
    r = np.sqrt(np.array([np.mean(v[k]) for v, k in zip(var, seen)])).reshape(batch)
    return z, r, cov
