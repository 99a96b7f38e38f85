"""The unbiased converted measurement of a polar plot (``immnet.data.radar.converted``) against a float64 Monte Carlo
of the conversion: its mean error is 0 to the Monte Carlo's precision where the plain conversion's is not, its
covariance given the truth is the Monte Carlo's, and its covariance given the measurement is that covariance averaged
over the truths the measurement could have come from."""

import numpy as np
import pytest

from immnet.data.radar import converted, from_polar, polar, polar_covariance

DEG = np.pi / 180
# (rho m, az deg, el deg, s_rho m, s_az deg, s_el deg): the radar stds at 150 km and 10 km, and large angle
# errors (2-5 deg) where the plain conversion's bias is tens to hundreds of metres; azimuths in every quadrant
CASES = [
    (150e3, 40.0, 3.0, 60.0, 0.2, 0.3),
    (10e3, 220.0, 1.0, 20.0, 0.05, 0.1),
    (100e3, 130.0, 20.0, 40.0, 5.0, 3.0),
    (10e3, 359.0, 60.0, 20.0, 2.0, 4.0),
    (60e3, 290.0, 8.0, 30.0, 3.0, 2.0),
]
N = 1_000_000


def draws(rho, az, el, s_rho, s_az, s_el, rng):
    return (rho + s_rho * rng.standard_normal(N), az + s_az * rng.standard_normal(N), el + s_el * rng.standard_normal(N))


@pytest.mark.parametrize("case", CASES)
def test_converted_mean_error_is_zero_and_its_covariance_the_monte_carlos(case):
    rho, az, el, s_rho, s_az, s_el = case
    az, el, s_az, s_el = az * DEG, el * DEG, s_az * DEG, s_el * DEG
    rng = np.random.default_rng(62)
    truth = from_polar(rho, az, el)
    m = draws(rho, az, el, s_rho, s_az, s_el, rng)
    z, R = converted(*m, s_rho, s_az, s_el)
    err, plain = z - truth, from_polar(*m) - truth
    se = err.std(0) / np.sqrt(N)
    assert np.all(np.abs(err.mean(0)) < 4.5 * se), (err.mean(0), se)
    # the plain conversion's bias, in closed form: (lambda_a lambda_e - 1) e, (lambda_a lambda_e - 1) n, (lambda_e - 1) u
    la, le = np.exp(-s_az**2 / 2), np.exp(-s_el**2 / 2)
    bias = truth * np.array([la * le - 1, la * le - 1, le - 1])
    np.testing.assert_allclose(plain.mean(0), bias, atol=4.5 * float(se.max()))
    if s_az * rho > 100:  # beyond 10 km 0.1 deg: measurably non-zero, what the unbiased conversion removes
        assert (np.abs(bias) / se).max() > 5, (bias, se)
    C = np.cov(err.T)
    _, C_truth = converted(rho, az, el, s_rho, s_az, s_el, given="truth")
    # the Monte Carlo's covariance to 1% of its largest entry (its sampling error is ~0.3%)
    assert np.abs(C - C_truth).max() < 0.01 * np.abs(C).max(), (C, C_truth)
    # what a filter uses, the covariance given each measurement, matches the Monte Carlo's on average to a few percent
    assert np.abs(R.mean(0) - C).max() < 0.04 * np.abs(C).max()


@pytest.mark.parametrize("case", CASES)
def test_covariance_given_the_measurement_averages_the_truths_it_could_have_come_from(case):
    rho, az, el, s_rho, s_az, s_el = case
    az, el, s_az, s_el = az * DEG, el * DEG, s_az * DEG, s_el * DEG
    rng = np.random.default_rng(7)
    # truths that give this measurement: measured - noise (the noise is symmetric, so measured + noise)
    truths = draws(rho, az, el, s_rho, s_az, s_el, rng)
    _, C = converted(*truths, s_rho, s_az, s_el, given="truth")
    _, R = converted(rho, az, el, s_rho, s_az, s_el)
    assert np.abs(C.mean(0) - R).max() < 0.005 * np.abs(R).max()
    assert np.all(np.linalg.eigvalsh(R) > 0)


def test_small_noise_is_the_first_order_covariance_and_the_plain_conversion():
    rho, az, el = np.array([20e3, 150e3]), np.array([0.3, 5.9]), np.array([0.02, 0.4])
    z, R = converted(rho, az, el, 30.0, 1e-4, 1e-4)
    np.testing.assert_allclose(z, from_polar(rho, az, el), rtol=1e-7)
    J = polar_covariance(rho, az, el, 30.0, 1e-4, 1e-4)
    np.testing.assert_allclose(R, J, atol=1e-6 * np.abs(J).max())
    back = polar(from_polar(rho, az, el))
    np.testing.assert_allclose(np.stack(back), np.stack([rho, az, el]), rtol=1e-12)


def test_given_must_be_measurement_or_truth():
    with pytest.raises(ValueError, match="given must be 'measurement' or 'truth'"):
        converted(1e4, 0.0, 0.0, 1.0, 0.01, 0.01, given="sensor")
