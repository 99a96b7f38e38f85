"""Measurement models (``immnet.imm.measurement``) and the robust update (``immnet.imm.kalman``'s module doc): the polar
extended Kalman update against Stone Soup's, a target crossing north, each detection's covariance in the IMM against
the isotropic filter (bit for bit) and FilterPy's IMMEstimator, and Huber's rule against a hand computation and an
outlier."""

import math

import numpy as np
import pytest
import torch
import yaml
from filterpy.kalman import IMMEstimator, KalmanFilter
from scipy.stats import multivariate_normal
from tensordict import TensorDict

from immnet import keys
from immnet.data.radar import from_polar
from immnet.filters.trackers import IMMTracker, KalmanFilterTracker
from immnet.imm.kalman import huber, update
from immnet.imm.measurement import (Isotropic, PerDetection, Polar, ToldStd, measurement_model, polar_update, to_polar,
                                    wrap)
from immnet.motion import ModelSet
from immnet.stages.filtering import FilterGain

DEG = math.pi / 180
REAL_IMM = yaml.safe_load(open("configs/methods/real-imm.yaml"))["init_args"]  # a real-flight IMMTracker


def _stonesoup_update(x, P, plot, sigma):
    """Stone Soup's ExtendedKalmanUpdater with CartesianToElevationBearingRange (bearing counter-clockwise from east:
    ``pi/2 - az``; its measurement ``(el, bearing, range)``): ``(x, P, innovation, S)`` in our plot's order."""
    from stonesoup.models.measurement.nonlinear import CartesianToElevationBearingRange
    from stonesoup.types.angle import Bearing, Elevation
    from stonesoup.types.array import StateVector
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.prediction import GaussianStatePrediction
    from stonesoup.types.state import State
    from stonesoup.updater.kalman import ExtendedKalmanUpdater

    class CentralDifferences(CartesianToElevationBearingRange):
        """Stone Soup's model with its Jacobian by central differences of its own function, 1 m steps (its default
        forward differences are good to 1e-4 only): truncation (1 m / 15 km)^2 and rounding 1e-16 x 15 km / 1 m, both
        below 1e-9."""

        def jacobian(self, state, **kwargs):
            J = np.zeros((3, 9))
            for i in (0, 3, 6):
                hi, lo = state.state_vector.astype(float).copy(), state.state_vector.astype(float).copy()
                hi[i] += 1.0
                lo[i] -= 1.0
                d = np.asarray(self.function(State(hi)) - self.function(State(lo)), float).ravel()
                J[:, i] = d / 2.0
            return J

    s_r, s_a, s_e = sigma
    mm = CentralDifferences(ndim_state=9, mapping=(0, 3, 6), noise_covar=np.diag([s_e**2, s_a**2, s_r**2]))
    det = Detection(StateVector([Elevation(plot[2]), Bearing(math.pi / 2 - plot[1]), plot[0]]), measurement_model=mm)
    hyp = SingleHypothesis(GaussianStatePrediction(StateVector(x), P), det)
    post = ExtendedKalmanUpdater(mm).update(hyp)
    mp = hyp.measurement_prediction
    order = [2, 1, 0]
    innov = np.asarray(det.state_vector - mp.state_vector, float).ravel()  # Stone Soup wraps the angles
    innov[1] = -innov[1]  # bearing = pi/2 - az
    flip = np.diag([1.0, -1.0, 1.0])
    S = flip @ np.asarray(mp.covar, float)[np.ix_(order, order)] @ flip
    return np.asarray(post.state_vector, float).ravel(), np.asarray(post.covar, float), innov[order], S


def _random_problem(rng, rho, az, el):
    pos = from_polar(rho, az, el)
    x = np.zeros(9)
    x[0::3] = pos
    x[1::3] = rng.normal(0, 100, 3)
    x[2::3] = rng.normal(0, 2, 3)
    A = rng.normal(size=(9, 9))
    P = A @ A.T + np.diag([400.0, 25, 1, 900, 25, 1, 300, 4, 1])
    return x, P


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("geometry", [(120e3, 45.0, 2.0), (30e3, 200.0, 10.0), (80e3, 359.95, 0.5), (15e3, 0.05, 30.0)])
def test_polar_update_is_stone_soups_extended_kalman_update(geometry, dtype):
    rng = np.random.default_rng(int(geometry[1] * 10))
    rho, az, el = geometry[0], geometry[1] * DEG, geometry[2] * DEG
    x, P = _random_problem(rng, rho, az, el)
    sigma = (40.0, 0.1 * DEG, 0.2 * DEG)
    # a plot off the prediction, its azimuth across north for the two geometries beside it
    plot = np.array([rho + 60.0, (az + 0.3 * DEG) % (2 * math.pi), el - 0.1 * DEG])
    want_x, want_P, want_nu, want_S = _stonesoup_update(x, P, plot, sigma)
    t = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
    got_x, got_P, ll = polar_update(t(x), t(P), t(plot), t(np.array(sigma)))
    assert got_x.dtype == dtype and got_P.dtype == dtype
    rtol = 1e-9 if dtype == torch.float64 else 2e-6
    np.testing.assert_allclose(got_x.double().numpy(), want_x, rtol=rtol, atol=rtol * 1e3)
    np.testing.assert_allclose(got_P.double().numpy(), want_P, rtol=rtol, atol=rtol * np.abs(want_P).max())
    want_ll = multivariate_normal(np.zeros(3), want_S).logpdf(want_nu)
    assert abs(float(ll) - want_ll) < (1e-8 if dtype == torch.float64 else 1e-4)


def test_polar_update_keeps_the_prior_where_the_plot_is_missed():
    rng = np.random.default_rng(0)
    x, P = _random_problem(rng, 50e3, 1.0, 0.1)
    x2 = torch.tensor(np.stack([x, x]))
    P2 = torch.tensor(np.stack([P, P]))
    plot = torch.tensor([[50e3, 1.0, 0.1], [float("nan")] * 3])
    xp, Pp, ll = polar_update(x2, P2, plot, torch.tensor([30.0, 1e-3, 1e-3]))
    assert torch.equal(xp[1], x2[1]) and torch.equal(Pp[1], P2[1]) and float(ll[1]) == 0.0
    assert not torch.equal(xp[0], x2[0])


def test_wrap_is_minus_pi_to_pi():
    a = torch.tensor([0.0, math.pi, -math.pi, 3 * math.pi / 2, -3 * math.pi / 2, 2 * math.pi - 1e-3, 7.0])
    w = wrap(a)
    assert torch.all((w > -math.pi) & (w <= math.pi))
    torch.testing.assert_close(torch.cos(w), torch.cos(a)), torch.testing.assert_close(torch.sin(w), torch.sin(a))


def _crossing(north: bool, T: int = 40):
    """A target at 60 km flying east at 200 m/s across north (or, rotated by 180 deg, west across south), its plots
    with seeded noise, as a batch of one track in ENU (the plots' plain conversion)."""
    g = np.random.default_rng(5)
    t = np.arange(T, dtype=float)
    e, n, u = 200.0 * (t - T / 2), np.full(T, 60e3), np.full(T, 5e3)
    sign = 1.0 if north else -1.0
    pos = np.stack([sign * e, sign * n, u], -1)
    rho, az, el = to_polar(torch.tensor(pos)).numpy().T
    noise = g.standard_normal((T, 3)) * np.array([30.0, 0.1 * DEG, 0.2 * DEG])
    z = from_polar(rho + noise[:, 0], az + noise[:, 1], el + noise[:, 2])
    states = np.zeros((T, 9))
    states[:, 0::3], states[:, 1] = pos, sign * 200.0
    batch = TensorDict({keys.MEASUREMENTS: torch.tensor(z)[None], keys.STATES: torch.tensor(states)[None],
                        keys.DT: torch.ones(1), keys.R: torch.full((1,), 30.0)}, batch_size=[1])
    return batch, az


def test_a_target_crossing_north_is_tracked_as_one_crossing_south():
    """The polar IMM on a target crossing north (az 359.x -> 0.x deg) gives the estimates it gives the same target
    rotated by 180 deg about the vertical, which crosses south without an azimuth wrap: the wrap costs nothing."""
    north, az = _crossing(True)
    south, _ = _crossing(False)
    assert (np.degrees(az[:20]) > 350).all() and (np.degrees(az[20:]) < 10).all()  # it crosses north at scan 20
    m = IMMTracker(**{**REAL_IMM, "r": {"sigma_range": 30.0, "sigma_azimuth_deg": 0.1, "sigma_elevation_deg": 0.2}})
    a = m.track(north)[keys.STATE][0]
    b = m.track(south)[keys.STATE][0]
    flip = torch.tensor([-1, -1, -1, -1, -1, -1, 1, 1, 1], dtype=torch.float64)
    torch.testing.assert_close(a, b * flip, rtol=1e-7, atol=1e-6)
    err = (a[:, 0::3] - north[keys.STATES][0, :, 0::3]).norm(dim=-1)
    assert float(err[19:23].max()) < 150.0  # no jump at the crossing: the range error's size at 60 km (0.1 deg = 105 m)


@pytest.fixture(scope="module")
def flights():
    from immnet.data.generate import generate
    from immnet.data.spec import DataSpec

    return generate(6, seed=62, spec=DataSpec(T=120))


def _with_cov(batch, cov):
    out = batch.clone()
    z = batch[keys.MEASUREMENTS]
    out[keys.MEAS_COV] = torch.where(torch.isnan(z).any(-1)[..., None, None], torch.nan, cov)
    return out


@pytest.mark.parametrize("intervals", ["fixed", "irregular"])
def test_each_detections_covariance_r2_identity_is_the_isotropic_filter_bit_for_bit(flights, intervals):
    batch = flights.clone()
    z = batch[keys.MEASUREMENTS]
    z[1, 7] = float("nan")  # a missed scan: its meas_cov NaN too
    if intervals == "irregular":
        batch[keys.TIME] = torch.cumsum(torch.rand(z.shape[:2], generator=torch.Generator().manual_seed(1),
                                                   dtype=torch.float64) + 0.5, 1)
    # a number: the fixed-interval fast path (or the core's loop); "data" (each track's r): the core's loop, where the
    # intervals differ (with one interval, r: data runs the core's loop and each detection's R the fast path: 1e-9)
    for r in (12.5, "data") if intervals == "irregular" else (12.5,):
        want = IMMTracker(**{**REAL_IMM, "r": r}, return_experts=True).track(batch)
        rb = torch.full((z.shape[0],), 12.5, dtype=torch.float64) if r != "data" else batch[keys.R]
        cov = (rb * rb)[:, None, None, None] * torch.eye(3, dtype=torch.float64)
        got = IMMTracker(**{**REAL_IMM, "r": "detection"}, return_experts=True).track(_with_cov(batch, cov.expand(*z.shape[:2], 3, 3)))
        for key in (keys.STATE, keys.MODE_PROBS, keys.EXPERT_POST):
            assert torch.equal(want[key].nan_to_num(-7.0), got[key].nan_to_num(-7.0)), (r, key)


def _filterpy_imm(F, Q, Pi, mu0, x0, P0, z, R):
    """FilterPy's IMMEstimator over one track, each filter's R set to the detection's before each update."""
    H = np.zeros((3, 9))
    H[0, 0] = H[1, 3] = H[2, 6] = 1.0
    filters = []
    for Fm, Qm in zip(F, Q):
        kf = KalmanFilter(9, 3)
        kf.F, kf.Q, kf.H = Fm, Qm, H
        kf.x, kf.P = x0.copy(), P0.copy()
        filters.append(kf)
    imm = IMMEstimator(filters, mu0.copy(), Pi)
    xs = [imm.x.copy()]
    for zt, Rt in zip(z[1:], R[1:]):
        imm.predict()
        for kf in filters:
            kf.R = Rt
        imm.update(zt)
        xs.append(imm.x.copy())
    return np.array(xs)


def test_each_detections_anisotropic_covariance_is_filterpys_imm(flights):
    z = flights[keys.MEASUREMENTS]
    B, T, _ = z.shape
    g = torch.Generator().manual_seed(3)
    # a radar's converted covariance shape: 40 m in range, 0.1-3 deg of 60 km across, rotated per detection
    A = torch.randn(B, T, 3, 3, generator=g, dtype=torch.float64) * 20.0
    cov = A @ A.transpose(-1, -2) + torch.diag(torch.tensor([25.0, 100.0, 400.0], dtype=torch.float64))
    batch = _with_cov(flights, cov)
    m = IMMTracker(**{**REAL_IMM, "r": "detection"})
    got = m.track(batch)[keys.STATE]
    F, Q, Pi, mu0 = m.matrices(1.0)
    for b in range(B):
        x0 = np.zeros(9)
        x0[0::3] = z[b, 0].numpy()
        P0 = np.diag([0.0, 300.0**2, 100.0] * 3)
        P0[0::3, 0::3] = cov[b, 0].numpy()
        want = _filterpy_imm(F.numpy(), Q.numpy(), Pi.numpy(), mu0.numpy(), x0, P0, z[b].numpy(), cov[b].numpy())
        # 1e-7 of the scale: the mode update's exponential carries float64 rounding of the two Joseph forms (FilterPy's
        # product, ours expanded) to 3e-8 of it at a turn's onset under these ill-conditioned covariances
        np.testing.assert_allclose(got[b].numpy(), want, rtol=1e-7, atol=1e-7 * np.abs(want).max())
    # and it is not the isotropic filter's
    iso = IMMTracker(**{**REAL_IMM, "r": 20.0}).track(flights)[keys.STATE]
    assert (iso - got).abs().max() > 1.0


def test_per_detection_covariance_is_refused_where_not_a_covariance(flights):
    z = flights[keys.MEASUREMENTS]
    cov = torch.eye(3, dtype=torch.float64).expand(*z.shape[:2], 3, 3).clone()
    m = IMMTracker(**{**REAL_IMM, "r": "detection"})
    with pytest.raises(ValueError, match="needs 'meas_cov'"):
        m.track(flights)
    bad = cov.clone()
    bad[2, 5, 0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"'meas_cov' of track 2, scan 5 is not a finite symmetric positive-definite"):
        m.track(flights.clone().set(keys.MEAS_COV, bad))
    bad = cov.clone()
    bad[0, 9, 2, 2] = -1.0
    with pytest.raises(ValueError, match=r"'meas_cov' of track 0, scan 9 is not"):
        m.track(flights.clone().set(keys.MEAS_COV, bad))
    with pytest.raises(ValueError, match=r"must be \[B, T, 3, 3\]"):
        PerDetection().R(flights.clone().set(keys.MEAS_COV, cov[:, :5]), torch.float64, "cpu")


@pytest.mark.parametrize("r, message", [("radar", "r must be a positive number, 'data'"),
                                        ({"sigma_range": 30}, "a polar measurement model takes exactly"),
                                        ({"sigma_range": -1, "sigma_azimuth_deg": 0.1, "sigma_elevation_deg": 0.1},
                                         "Polar.sigma_range must be a positive number")])
def test_a_measurement_model_that_is_none_is_refused(r, message):
    with pytest.raises(ValueError, match=message):
        measurement_model(r)
    with pytest.raises(ValueError, match=message):
        IMMTracker(**{**REAL_IMM, "r": r})


CV_KF = dict(model={"class_path": "immnet.motion.ConstantVelocity"}, sigma_q=5.0)
POLAR = {"sigma_range": 30, "sigma_azimuth_deg": 0.1, "sigma_elevation_deg": 0.1}


@pytest.mark.parametrize("make, r, kind", [("kf", None, "Estimated"), ("kf", "detection", "PerDetection"),
                                           ("kf", POLAR, "Polar"), ("imm", None, "Estimated"), ("gain", POLAR, "Polar")])
def test_a_measurement_model_a_filter_does_not_take_is_refused_by_its_kind(make, r, kind):
    """One line naming the kinds the filter takes and the kind it was given: the Kalman filter neither an estimated
    ``r``, each detection's covariance nor the polar model, the IMM no estimated ``r``, IMMNet's filter experts not the
    polar model."""
    build = {"kf": lambda: KalmanFilterTracker(**CV_KF, r=r), "imm": lambda: IMMTracker(**{**REAL_IMM, "r": r}),
             "gain": lambda: FilterGain(ModelSet.from_config(REAL_IMM["model_set"]), r=r)}[make]
    with pytest.raises(ValueError, match=rf"^r must be .+, got .+ \({kind}, which this filter does not take\)$") as err:
        build()
    if make == "kf" and r is None:
        assert str(err.value) == ("r must be a positive number or 'data' (each track's own r), got None (Estimated, "
                                  "which this filter does not take)")


def test_a_model_given_as_itself_is_its_configurations_spelling(flights):
    """A filter given the model itself filters as with its spelling in a configuration: the Kalman filter and the IMM
    with ``Isotropic(30.0)`` as with ``30``, ``ToldStd()`` as with ``"data"``, ``PerDetection()`` as with
    ``"detection"`` (bit for bit); IMMNet's filter experts read the same step inputs."""
    batch = _with_cov(flights, 30.0**2 * torch.eye(3, dtype=torch.float64))
    for spelling, model in ((30, Isotropic(30.0)), ("data", ToldStd()), ("detection", PerDetection())):
        assert measurement_model(spelling) == model and measurement_model(model) is model
        imm = [IMMTracker(**{**REAL_IMM, "r": r}).track(batch)[keys.STATE] for r in (spelling, model)]
        assert torch.equal(imm[0].nan_to_num(0), imm[1].nan_to_num(0))
        gains = [FilterGain(ModelSet.from_config(REAL_IMM["model_set"]), r=r) for r in (spelling, model)]
        assert gains[0].in_keys == gains[1].in_keys and gains[0].measurement == gains[1].measurement == model
        if not isinstance(model, PerDetection):
            kf = [KalmanFilterTracker(**CV_KF, r=r).track(batch)[keys.STATE] for r in (spelling, model)]
            assert torch.equal(kf[0].nan_to_num(0), kf[1].nan_to_num(0))


def test_robust_setting_is_checked():
    for bad in (0.0, -1.0, float("inf"), True, "3"):
        with pytest.raises(ValueError, match="robust must be None \\(off\\) or Huber's k"):
            IMMTracker(**{**REAL_IMM, "robust": bad})
    with pytest.raises(ValueError, match="modes per axis track with IMMNet's step"):
        IMMTracker(**{**REAL_IMM, "robust": 3.0, "modes": "axis", "sigma_q": 0.5,
                       "model_set": {"models": REAL_IMM["model_set"]["models"][:2]}})


def test_huber_rule_against_a_hand_computation():
    x = torch.zeros(9, dtype=torch.float64)
    P = torch.eye(9, dtype=torch.float64)
    z = torch.tensor([6.0, 0.0, 0.0], dtype=torch.float64)  # S = P_pos + R = 2 I: d = 6 / sqrt(2) = 4.243
    k = 2.0
    xr, Pr, llr = update(x, P, z, R=1.0, robust=k)
    d = 6.0 / math.sqrt(2.0)
    w = k / d
    assert abs(float(xr[0]) - w * 0.5 * 6.0) < 1e-15  # K = P H^T S^-1 = 0.5 on the position: x += w K nu
    assert abs(float(Pr[0, 0]) - (1.0 - w * 0.5)) < 1e-15  # P - w K H P
    assert float(Pr[1, 1]) == 1.0 and float(xr[1]) == 0.0
    want_ll = -0.5 * (2 * k * d - k * k + 3 * math.log(2.0) + 3 * math.log(2 * math.pi))
    assert abs(float(llr) - want_ll) < 1e-12
    w_t, m_t = huber(torch.tensor([1.0, 4.0, 25.0], dtype=torch.float64), 2.0)
    assert w_t.tolist() == [1.0, 1.0, 0.4] and m_t.tolist() == [1.0, 4.0, 2 * 2 * 5 - 4]
    # within k, the plain update bit for bit
    z = torch.tensor([1.0, -0.5, 0.3], dtype=torch.float64)
    for a, b in zip(update(x, P, z, R=1.0, robust=k), update(x, P, z, R=1.0)):
        assert torch.equal(a, b)


def test_robust_filter_without_outliers_is_the_plain_filter_where_d_is_below_k(flights):
    kf = dict(model={"class_path": "immnet.motion.ConstantVelocity"}, r="data", sigma_q=5.0)
    plain = KalmanFilterTracker(**kf).track(flights)[keys.STATE]
    assert torch.equal(KalmanFilterTracker(**kf, robust=1e6).track(flights)[keys.STATE].nan_to_num(0),
                       plain.nan_to_num(0))
    imm = IMMTracker(**{**REAL_IMM, "r": "data"}).track(flights)[keys.STATE]
    torch.testing.assert_close(IMMTracker(**{**REAL_IMM, "r": "data", "robust": 1e6}).track(flights)[keys.STATE], imm,
                               rtol=1e-9, atol=1e-7, equal_nan=True)


def _straight_tracks(n: int, T: int, r: float, seed: int):
    g = np.random.default_rng(seed)
    t = np.arange(T, dtype=float)
    p0 = g.uniform(-20e3, 20e3, (n, 1, 3))
    v = g.normal(0, 150, (n, 1, 3)) * np.array([1, 1, 0.05])
    pos = p0 + v * t[None, :, None]
    states = np.zeros((n, T, 9))
    states[..., 0::3], states[..., 1::3] = pos, np.broadcast_to(v, pos.shape)
    z = pos + r * g.standard_normal(pos.shape)
    return states, z


def test_huber_weighs_an_isolated_far_plot_and_takes_the_second_of_a_run_whole():
    """``KalmanFilterTracker(robust=k)`` against FilterPy's Kalman filter run by hand in float64: a plot beyond ``k``
    (``d = sqrt(y^T S^-1 y)``) that follows a plot within ``k`` is weighed by Huber (FilterPy's update with ``R' = R +
    (1/w - 1) S``, ``w = k / d``), one that follows a far plot is taken whole (a maneuver gives far plots scan after
    scan, an outlier one). Tracks with one outlier (scan 12) and a run of two (scans 25, 26), 800 m off at r = 20 m;
    the second of the run moves the track by the plain gain, far from where weighing every plot would leave it."""
    from immnet.filters.imm import initial_state

    r, k, T, n = 20.0, 2.5, 40, 3
    states, z = _straight_tracks(n, T, r, seed=7)
    g = np.random.default_rng(3)
    off = g.standard_normal((n, 3))
    off = 800.0 * off / np.linalg.norm(off, axis=-1, keepdims=True)
    for at in (12, 25, 26):
        z[:, at] += off
    model = {"class_path": "immnet.motion.ConstantVelocity", "init_args": {"noise": "continuous"}}
    batch = TensorDict({keys.MEASUREMENTS: torch.tensor(z), keys.STATES: torch.tensor(states), keys.DT: torch.ones(n)},
                       batch_size=[n])
    tracker = KalmanFilterTracker(model, r=r, sigma_q=2.0, robust=k)
    ours = tracker.track(batch)[keys.STATE].numpy()
    F = tracker.model.F(1.0, dtype=torch.float64).numpy()
    Q = tracker.model.Q(2.0, 1.0, dtype=torch.float64).numpy()
    x0, P0 = initial_state(torch.tensor(z), r)
    H = np.zeros((3, 9))
    H[[0, 1, 2], [0, 3, 6]] = 1.0

    def reference(isolated: bool):
        out = np.zeros((n, T, 9))
        for b in range(n):
            kf = KalmanFilter(dim_x=9, dim_z=3)
            kf.x, kf.P, kf.F, kf.Q, kf.H, kf.R = x0[b].numpy().copy(), P0[b].numpy().copy(), F, Q, H, r * r * np.eye(3)
            out[b, 0], before = kf.x, False
            for t in range(1, T):
                kf.predict()
                y = z[b, t] - H @ kf.x
                S = H @ kf.P @ H.T + kf.R
                d = math.sqrt(y @ np.linalg.solve(S, y))
                w = k / d if d > k and not (isolated and before) else 1.0
                kf.update(z[b, t], R=kf.R + (1.0 / w - 1.0) * S)
                out[b, t], before = kf.x, d > k
        return out

    want = reference(isolated=True)
    np.testing.assert_allclose(ours, want, rtol=0, atol=1e-6 * np.abs(want).max())
    every = reference(isolated=False)  # Huber's weight on every far plot
    assert np.allclose(want[:, :26], every[:, :26], rtol=0, atol=1e-6 * np.abs(want).max())
    assert (np.linalg.norm(want[:, 26, 0::3] - every[:, 26, 0::3], axis=-1) > 100.0).all()


def test_a_ten_r_outlier_moves_the_robust_imm_much_less_than_the_plain_one():
    """A seeded Monte Carlo: 200 straight tracks at r = 10 m, one detection 10 r off (scan 30) in a random direction;
    the error the outlier adds at that scan (RMSE over the tracks, less the same filter's without the outlier), plain
    against robust (k = 3): the robust filter's is a third of the plain's (its pull is w = k / d ~ 3 / 9 of it)."""
    r, T, at = 10.0, 50, 30
    states, clean = _straight_tracks(200, T, r, seed=62)
    g = np.random.default_rng(1)
    direction = g.standard_normal((200, 3))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    hit = clean.copy()
    hit[:, at] += 10 * r * direction
    excess = {}
    for k in (None, 3.0):
        rmse = []
        for z in (clean, hit):
            batch = TensorDict({keys.MEASUREMENTS: torch.tensor(z), keys.STATES: torch.tensor(states),
                                keys.DT: torch.ones(200), keys.R: torch.full((200,), r, dtype=torch.float64)},
                               batch_size=[200])
            est = IMMTracker(**{**REAL_IMM, "r": r, "robust": k}).track(batch)[keys.STATE]
            e = (est[:, at, 0::3] - batch[keys.STATES][:, at, 0::3]).norm(dim=-1)
            rmse.append(float(e.pow(2).mean().sqrt()))
        excess[k] = rmse[1] - rmse[0]
    assert excess[None] > 30.0 and excess[3.0] < 0.4 * excess[None], excess


def test_polar_robust_update_shrinks_an_outliers_pull():
    rng = np.random.default_rng(2)
    x, P = _random_problem(rng, 60e3, 0.5, 0.05)
    sig = torch.tensor([30.0, 0.1 * DEG, 0.2 * DEG], dtype=torch.float64)
    plot = to_polar(torch.tensor(x[0::3])) + torch.tensor([300.0, 0.0, 0.0], dtype=torch.float64)
    xp, _, _ = polar_update(torch.tensor(x), torch.tensor(P), plot, sig)
    xr, _, _ = polar_update(torch.tensor(x), torch.tensor(P), plot, sig, robust=3.0)
    pull, pull_r = ((v[0::3] - torch.tensor(x[0::3])).norm() for v in (xp, xr))
    assert pull_r < 0.5 * pull
    assert isinstance(Polar(30.0, 1e-3, 1e-3).needs, tuple)


def test_polar_start_covariance_is_the_conversions_first_order_covariance():
    from immnet.data.radar import polar_covariance

    plots = np.array([[80e3, 0.2, 0.05], [20e3, 5.0, 0.4]])
    sig = np.array([[40.0, 0.002, 0.003], [20.0, 0.001, 0.004]])
    z0 = torch.tensor(from_polar(*plots.T))
    got = Polar(1.0, 1.0, 1.0).initial_cov(z0, torch.tensor(sig))
    want = polar_covariance(*plots.T, *sig.T)
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-9, atol=1e-9 * np.abs(want).max())
