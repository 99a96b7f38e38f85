"""WGS-84 geodesy and the radar's polar conversion: known points, round trips, the converted covariance."""

import numpy as np
import pytest

from immnet.data import geodesy, radar

SITE = (48.9, 2.47, 120.0)
R_EARTH = 6371000.0


def test_ecef_of_known_points():
    assert np.allclose(geodesy.geodetic_to_ecef(0.0, 0.0, 0.0), [6378137.0, 0.0, 0.0], atol=1e-9)
    assert np.allclose(geodesy.geodetic_to_ecef(0.0, 90.0, 0.0), [0.0, 6378137.0, 0.0], atol=1e-6)
    assert np.allclose(geodesy.geodetic_to_ecef(90.0, 0.0, 0.0), [0.0, 0.0, geodesy.B], atol=1e-6)


def test_site_is_origin_and_north_east_drop_by_curvature():
    assert np.allclose(geodesy.geodetic_to_enu(*SITE, SITE), 0.0, atol=1e-8)
    lat0, lon0, h0 = SITE
    # 1 km along the meridian / the parallel, at the site's height (radii of curvature there + h0)
    m = geodesy.A * (1 - geodesy.E2) / (1 - geodesy.E2 * np.sin(np.radians(lat0)) ** 2) ** 1.5 + h0  # meridian radius
    n = geodesy.A / np.sqrt(1 - geodesy.E2 * np.sin(np.radians(lat0)) ** 2) + h0  # prime vertical radius
    north = geodesy.geodetic_to_enu(lat0 + np.degrees(1000.0 / m), lon0, h0, SITE)
    east = geodesy.geodetic_to_enu(lat0, lon0 + np.degrees(1000.0 / (n * np.cos(np.radians(lat0)))), h0, SITE)
    assert north[0] == pytest.approx(0.0, abs=1e-6) and north[1] == pytest.approx(1000.0, abs=0.01)
    assert north[2] == pytest.approx(-1000.0 ** 2 / (2 * m), rel=1e-3)  # ~ -0.078 m
    assert east[0] == pytest.approx(1000.0, abs=0.01)
    # a parallel is a small circle: it bends toward the pole by d^2 tan(lat) / (2 N) (9 cm here)
    assert east[1] == pytest.approx(1000.0 ** 2 * np.tan(np.radians(lat0)) / (2 * n), rel=1e-3)
    assert east[2] == pytest.approx(-1000.0 ** 2 / (2 * n), rel=1e-3)
    assert -0.09 < north[2] < -0.07 and -0.09 < east[2] < -0.07
    # 200 km north: the drop is d^2 / (2 R), about 3.1 km
    far = geodesy.geodetic_to_enu(lat0 + np.degrees(200e3 / m), lon0, h0, SITE)
    assert far[2] == pytest.approx(-(200e3 ** 2) / (2 * R_EARTH), rel=0.02)


def test_round_trips():
    rng = np.random.default_rng(0)
    lat, lon, h = rng.uniform(-89, 89, 500), rng.uniform(-180, 180, 500), rng.uniform(-100, 15000, 500)
    back = geodesy.ecef_to_geodetic(geodesy.geodetic_to_ecef(lat, lon, h))
    assert np.allclose(back[0], lat, atol=1e-10) and np.allclose(back[1], lon, atol=1e-10)
    assert np.allclose(back[2], h, atol=1e-6)
    enu = rng.uniform(-2e5, 2e5, (500, 3))
    assert np.allclose(geodesy.geodetic_to_enu(*geodesy.enu_to_geodetic(enu, SITE), SITE), enu, atol=1e-6)


def test_local_step_is_the_distance():
    m = geodesy.A * (1 - geodesy.E2) / (1 - geodesy.E2 * np.sin(np.radians(45.0)) ** 2) ** 1.5
    d = geodesy.local_step(np.array([45.0, 45.0 + np.degrees(500.0 / m)]), np.array([3.0, 3.0]))
    assert d[0] == pytest.approx(500.0, abs=1e-3)


def test_polar_round_trip_and_converted_covariance():
    enu = np.array([[30e3, 80e3, 6e3], [-120e3, 10e3, 9e3]])
    rho, az, el = radar.polar(enu)
    assert np.allclose(radar.from_polar(rho, az, el), enu, atol=1e-6)
    s = (20.0, 1e-3, 1e-3)  # 20 m in range, 1 mrad in azimuth and elevation
    cov = radar.polar_covariance(rho, az, el, *s)
    rng = np.random.default_rng(1)
    for i in range(2):
        noise = rng.standard_normal((200_000, 3)) * s
        z = radar.from_polar(rho[i] + noise[:, 0], az[i] + noise[:, 1], el[i] + noise[:, 2])
        mc = np.cov(z.T)
        assert np.allclose(mc, cov[i], rtol=0.02, atol=0.02 * np.sqrt(np.outer(np.diag(mc), np.diag(mc))).max())
