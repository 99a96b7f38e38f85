"""WGS-84 geodesy: geodetic <-> Earth-centred Earth-fixed (ECEF) <-> local east-north-up (ENU).

Exact formulas in float64, Earth curvature kept (docs/real-data.md, "Real flights"). With the semi-major
axis ``a``, flattening ``f``, ``e^2 = f (2 - f)`` and the prime-vertical radius
``N(phi) = a / sqrt(1 - e^2 sin^2 phi)``, a point at latitude ``phi``, longitude ``lam`` and height
``h`` above the ellipsoid is::

    X = (N + h) cos phi cos lam,   Y = (N + h) cos phi sin lam,   Z = (N (1 - e^2) + h) sin phi

and its ENU coordinates at a site ``(phi0, lam0, h0)`` (ECEF ``P0``) are ``R (P - P0)`` with the rows
of ``R`` the site's east, north and up unit vectors::

    e = (-sin lam0, cos lam0, 0)
    n = (-sin phi0 cos lam0, -sin phi0 sin lam0, cos phi0)
    u = (cos phi0 cos lam0, cos phi0 sin lam0, sin phi0)

A point ``d`` metres north of the site at the site's height is therefore below the site's horizontal
plane by about ``d^2 / (2 R)`` (8 cm at 1 km, 3.1 km at 200 km). The inverse (ECEF -> geodetic) is
Bowring's iteration, converged to float64 precision in a few steps for any height of aircraft.
"""

from __future__ import annotations

import numpy as np

A = 6378137.0
"""WGS-84 semi-major axis (m)."""
F = 1.0 / 298.257223563
"""WGS-84 flattening."""
E2 = F * (2.0 - F)
"""First eccentricity squared."""
B = A * (1.0 - F)
"""Semi-minor axis (m)."""


def _site(site) -> tuple[float, float, float]:
    lat0, lon0, h0 = (float(v) for v in site)
    if not (-90.0 <= lat0 <= 90.0 and -180.0 <= lon0 <= 360.0 and np.isfinite(h0)):
        raise ValueError(f"site (lat, lon, h) = {site} is not a valid geodetic position (degrees, degrees, m)")
    return lat0, lon0, h0


def geodetic_to_ecef(lat, lon, h) -> np.ndarray:
    """Latitude and longitude (degrees) and height above the ellipsoid (m) -> ECEF ``[..., 3]`` (m)."""
    phi, lam = np.radians(np.asarray(lat, np.float64)), np.radians(np.asarray(lon, np.float64))
    h = np.asarray(h, np.float64)
    sp, cp = np.sin(phi), np.cos(phi)
    n = A / np.sqrt(1.0 - E2 * sp * sp)
    return np.stack([(n + h) * cp * np.cos(lam), (n + h) * cp * np.sin(lam), (n * (1.0 - E2) + h) * sp], -1)


def ecef_to_geodetic(xyz) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF ``[..., 3]`` (m) -> ``(lat, lon, h)`` (degrees, degrees, m), by Bowring's iteration."""
    xyz = np.asarray(xyz, np.float64)
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    p = np.hypot(x, y)
    lon = np.arctan2(y, x)
    ep2 = (A * A - B * B) / (B * B)
    beta = np.arctan2(z * A, p * B)  # reduced latitude, first guess
    for _ in range(6):  # converges to ~1e-15 rad in 2-3 steps at aircraft heights
        phi = np.arctan2(z + ep2 * B * np.sin(beta) ** 3, p - E2 * A * np.cos(beta) ** 3)
        beta = np.arctan2((1.0 - F) * np.sin(phi), np.cos(phi))
    sp = np.sin(phi)
    n = A / np.sqrt(1.0 - E2 * sp * sp)
    # h from the component along the normal: exact at any latitude, poles included
    h = p * np.cos(phi) + z * sp - n * (1.0 - E2 * sp * sp)
    return np.degrees(phi), np.degrees(lon), h


def enu_rotation(lat0, lon0) -> np.ndarray:
    """The rows of the site's east, north and up unit vectors in ECEF ``[3, 3]`` (``[..., 3, 3]`` for sites
    ``lat0``, ``lon0`` of shape ``[...]``)."""
    phi, lam = np.radians(np.asarray(lat0, np.float64)), np.radians(np.asarray(lon0, np.float64))
    sp, cp, sl, cl = np.sin(phi), np.cos(phi), np.sin(lam), np.cos(lam)
    return np.stack([np.stack([-sl, cl, np.zeros_like(phi)], -1), np.stack([-sp * cl, -sp * sl, cp], -1),
                     np.stack([cp * cl, cp * sl, sp], -1)], -2)


def geodetic_to_enu(lat, lon, h, site) -> np.ndarray:
    """Latitude, longitude (degrees) and height (m) -> ENU ``[..., 3]`` (m) at ``site = (lat0, lon0, h0)`` (degrees,
    degrees, m): ``R (P - P0)`` in ECEF."""
    lat0, lon0, h0 = _site(site)
    return (geodetic_to_ecef(lat, lon, h) - geodetic_to_ecef(lat0, lon0, h0)) @ enu_rotation(lat0, lon0).T


def enu_to_geodetic(enu, site) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ENU ``[..., 3]`` (m) at ``site`` -> ``(lat, lon, h)`` (degrees, degrees, m), through ECEF ``R^T enu + P0``."""
    lat0, lon0, h0 = _site(site)
    return ecef_to_geodetic(np.asarray(enu, np.float64) @ enu_rotation(lat0, lon0) + geodetic_to_ecef(lat0, lon0, h0))


def local_step(lat, lon) -> np.ndarray:
    """The horizontal distance (m) between consecutive points of ``lat, lon [n]`` (degrees), ``[n - 1]``:
    the ECEF chord between them at height 0 (it differs from the arc by ``d^3 / (24 R^2)``, 1 micrometre
    at 1 km)."""
    p = geodetic_to_ecef(lat, lon, np.zeros_like(np.asarray(lat, np.float64)))
    return np.linalg.norm(np.diff(p, axis=0), axis=-1)
