"""IMM-EKF against an independent float64 numpy IMM written from docs/spec.md's equations, scan by scan.

The reference loops over tracks, filters and mixing pairs, writes the coordinated turn out from docs/spec.md
section 2, takes the turn filters' Jacobians by central differences and inverts ``S`` with numpy: it
shares no code with ``immnet.stages.filtering`` (which IMM-EKF runs) beyond the constants of the generator it is
told. It starts as IMMNet does (two detections).
"""

import math

import numpy as np
import pytest
import torch

from immnet import keys
from immnet.config import REPO_ROOT
from immnet.evaluation.metrics import position_error, rmse
from immnet.filters.methods import build_method
from immnet.filters import IMMEKF, ClairvoyantKF

DEG = math.pi / 180.0
ACC_VAR = [(3.0**3 - 0.5**3) / (3.0 * 2.5) / 2.0] * 2 + [0.6**2 / 12.0]  # docs/spec.md section 2: |a| ~ U[0.5, 3] at a uniform direction; U[-0.3, 0.3]
W_MEAN, W_VAR = 5.5 * DEG, (9.0 * DEG) ** 2 / 12.0  # |w| ~ U[1, 10] deg/s


def _noise_var_reference(alt, r0, k0, times=None):
    """The running r^2 estimate; at scan ``times`` the third divided difference, whose weights
    ``c_k = 1 / prod_{j != k} (t_k - t_j)`` cancel any quadratic, normalized to E = r^2 by ``sum c_k^2``."""
    out, total, count = [], 0.0, 0
    for t in range(len(alt)):
        if t >= 3:
            if times is None:
                d3, norm = alt[t] - 3 * alt[t - 1] + 3 * alt[t - 2] - alt[t - 3], 20.0
            else:
                s = times[t - 3 : t + 1]
                c = np.array([1.0 / np.prod([s[k] - s[j] for j in range(4) if j != k]) for k in range(4)])
                d3, norm = c @ alt[t - 3 : t + 1], c @ c
            if np.isfinite(d3):
                total, count = total + d3 * d3 / norm, count + 1
        out.append((k0 * r0 * r0 + total) / (k0 + count))
    return np.array(out)


def _f(j, x, dt):
    """Filter ``j``'s motion (CV, CA, CT+, CT-) of ``[lx, vx, ax, ly, vy, ay, lz, vz, az, w]``, from docs/spec.md."""
    lx, vx, ax, ly, vy, ay, lz, vz, az, w = x
    if j == 0:
        return np.array([lx + dt * vx, vx, 0, ly + dt * vy, vy, 0, lz + dt * vz, vz, 0, w])
    if j == 1:
        h = dt * dt / 2
        return np.array([lx + dt * vx + h * ax, vx + dt * ax, ax, ly + dt * vy + h * ay, vy + dt * ay, ay,
                         lz + dt * vz + h * az, vz + dt * az, az, w])
    s, c = math.sin(w * dt), math.cos(w * dt)
    vx1, vy1 = c * vx - s * vy, s * vx + c * vy
    return np.array([lx + s / w * vx - (1 - c) / w * vy, vx1, -w * vy1, ly + (1 - c) / w * vx + s / w * vy, vy1, w * vx1,
                     lz + dt * vz, vz, 0, w])


def _jacobian(j, x, dt):
    """Central differences, at the positions moved to 0 (the motion is translation-invariant), so that
    the differences are not lost in the positions' magnitude."""
    J, x = np.zeros((10, 10)), x.copy()
    x[0:9:3] = 0.0
    for k in range(10):
        h = 1e-5 * max(1.0, abs(x[k])) if k < 9 else 1e-6
        e = np.zeros(10)
        e[k] = h
        J[:, k] = (_f(j, x + e, dt) - _f(j, x - e, dt)) / (2 * h)
    return J


def _reference(z, p_stay, sigma_q, r0, k0, dt=1.0, lo=1.0 * DEG, hi=30.0 * DEG, adapt=None):
    """One track ``z [T, 3]`` (NaN = missed): fused states ``[T, 9]`` and mode probabilities ``[T, 4]``.
    ``dt``: the interval, or the interval before each scan ``[T]`` (F, Q and the start of each step's own).
    ``adapt`` ``(rate, deadband, nis_clip, max_scale)``: Q times ``lambda``, whose log moves by
    ``rate (min(min_j NIS_j / 3, nis_clip) - 1 - deadband)`` on a detected scan, clipped to [0, log max_scale]."""
    T, M = len(z), 4
    irregular = np.ndim(dt) > 0
    dts = np.broadcast_to(np.asarray(dt, dtype=float), (T,))
    times = np.cumsum(dts)
    r2 = _noise_var_reference(z[:, 2], r0, k0, times if irregular else None)
    Pi = np.full((M, M), (1 - p_stay) / 3)
    np.fill_diagonal(Pi, p_stay)

    def noise(d):
        G = np.array([d * d / 2, d, 0.0])
        Q = np.zeros((10, 10))
        for a in range(3):
            Q[3 * a:3 * a + 3, 3 * a:3 * a + 3] = sigma_q**2 * np.outer(G, G)
        return Q
    # IMMNet's start (immnet.stages.network): the first detection's position, at the second the differenced
    # velocity; the filters' covariance from the r^2 known before it, their turn rates at the nominal +/-5 deg/s
    detected = [t for t in range(T) if np.isfinite(z[t]).all()]
    first, second = detected[0], detected[1]
    x0 = np.zeros(10)
    x0[0:9:3] = z[second]
    e = times[second] - times[first] if irregular else (second - first) * dt  # the time between them
    x0[1:9:3] = (z[second] - z[first]) / e
    e = e if irregular else dt  # the start covariance at the nominal interval where all are one
    rs = r2[second - 1]
    P0 = np.zeros((10, 10))
    for a in range(3):
        p, v, c = 3 * a, 3 * a + 1, 3 * a + 2
        P0[p, p], P0[v, v], P0[p, v], P0[v, p], P0[c, c] = rs, 2 * rs / e**2, rs / e, rs / e, ACC_VAR[a]

    def enter(j, x, P):  # the generator's draw at a switch into j
        x, P = x.copy(), P.copy()
        if j == 1:
            for a, v in zip((2, 5, 8), ACC_VAR):
                x[a] = 0
                P[a, :] = P[:, a] = 0
                P[a, a] = v
        if j >= 2:
            x[9] = W_MEAN if j == 2 else -W_MEAN
            P[9, :] = P[:, 9] = 0
            P[9, 9] = W_VAR
        return x, P

    xs, Ps = [], []
    for j in range(M):
        x, P = x0.copy(), P0.copy()
        if j >= 2:
            x[9], P[9, 9] = (5.0 if j == 2 else -5.0) * DEG, (5.0 * DEG) ** 2
        xs.append(x)
        Ps.append(P)
    mu = np.full(M, 0.25)
    start = np.zeros(9)
    start[0:9:3] = z[first]
    out = [start if t < second else x0[:9] for t in range(second + 1)]
    probs = [mu.copy() for _ in range(second + 1)]
    log_scale = 0.0
    for t in range(second + 1, T):
        cbar = Pi.T @ mu
        new_x, new_P, logl, nis = [], [], [], []
        for j in range(M):
            parts = [(mu[i] * Pi[i, j] / cbar[j],) + ((xs[i], Ps[i]) if i == j else enter(j, xs[i], Ps[i])) for i in range(M)]
            xm = sum(w * xi for w, xi, _ in parts)
            Pm = sum(w * (Pi_ + np.outer(xi - xm, xi - xm)) for w, xi, Pi_ in parts)
            J = _jacobian(j, xm, dts[t])
            xp, Pp = _f(j, xm, dts[t]), J @ Pm @ J.T + np.exp(log_scale) * noise(dts[t])
            if np.isfinite(z[t]).all():
                y = z[t] - xp[0:9:3]
                S = Pp[0:9:3][:, 0:9:3] + r2[t] * np.eye(3)
                nis.append(y @ np.linalg.solve(S, y))
                K = Pp[:, 0:9:3] @ np.linalg.inv(S)
                xp, Pp = xp + K @ y, Pp - K @ S @ K.T
                logl.append(-0.5 * (y @ np.linalg.solve(S, y) + np.log(np.linalg.det(S)) + 3 * np.log(2 * np.pi)))
            else:
                logl.append(0.0)
            if j >= 2:
                xp[9] = np.clip(xp[9], lo, hi) if j == 2 else np.clip(xp[9], -hi, -lo)
            new_x.append(xp)
            new_P.append(Pp)
        xs, Ps = new_x, new_P
        if adapt is not None and nis:
            rate, deadband, clip, max_scale = adapt
            log_scale = float(np.clip(log_scale + rate * (min(min(nis) / 3, clip) - 1 - deadband), 0.0, np.log(max_scale)))
        a = np.log(cbar) + np.array(logl)
        mu = np.exp(a - a.max())
        mu /= mu.sum()
        out.append(sum(m * xj[:9] for m, xj in zip(mu, xs)))
        probs.append(mu.copy())
    out, probs = np.array(out), np.array(probs)
    out[:first], probs[:first] = np.nan, np.nan  # no estimate before the first detection
    return out, probs


@pytest.fixture(scope="module")
def data():
    from immnet.data.spec import DataSpec

    generate = pytest.importorskip("immnet.data.generate").generate
    return generate(4, seed=707, spec=DataSpec(T=120, min_segment=30))


@pytest.mark.parametrize("missed", [False, True], ids=["all-detected", "missed"])
def test_imm_ekf_equals_a_numpy_imm(data, missed):
    data = data.clone()
    if missed:
        data[keys.MEASUREMENTS][0, 30:33] = float("nan")
        data[keys.MEASUREMENTS][2, 0] = float("nan")  # the track starts at its first detection
    method = IMMEKF(p_stay=0.97, sigma_q=0.3, r0=3.0, k0=2.0)
    out = method.track(data)
    for b in range(data.shape[0]):
        states, probs = _reference(data[keys.MEASUREMENTS][b].numpy(), 0.97, 0.3, 3.0, 2.0)
        np.testing.assert_allclose(out[keys.STATE][b].numpy(), states, rtol=1e-7, atol=1e-6)
        np.testing.assert_allclose(out[keys.MODE_PROBS][b].numpy(), probs, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("missed", [False, True], ids=["all-detected", "missed"])
def test_adaptive_imm_ekf_equals_a_numpy_imm(data, missed):
    """Issue 20, item 7: ``IMMEKF(adapt=...)`` (adaptive process noise, immnet.imm.adaptive) is the numpy
    IMM with its Q scaled per track by the rule, written out here; assuming a quarter of the truth's
    sigma_q, the scale grows (the states differ from the fixed-noise filter's)."""
    data = data.clone()
    if missed:
        data[keys.MEASUREMENTS][0, 30:33] = float("nan")
    adapt = {"rate": 0.1, "deadband": 0.1, "nis_clip": 3.0, "max_scale": 50.0}
    out = IMMEKF(p_stay=0.97, sigma_q=0.05, r0=3.0, k0=2.0, adapt=adapt).track(data)
    fixed = IMMEKF(p_stay=0.97, sigma_q=0.05, r0=3.0, k0=2.0).track(data)
    assert (out[keys.STATE] - fixed[keys.STATE]).abs().max() > 0.1
    for b in range(data.shape[0]):
        states, probs = _reference(data[keys.MEASUREMENTS][b].numpy(), 0.97, 0.05, 3.0, 2.0, adapt=tuple(adapt.values()))
        np.testing.assert_allclose(out[keys.STATE][b].numpy(), states, rtol=1e-7, atol=1e-6)
        np.testing.assert_allclose(out[keys.MODE_PROBS][b].numpy(), probs, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("missed", [False, True], ids=["all-detected", "missed"])
def test_imm_ekf_at_irregular_intervals_equals_a_numpy_imm(missed):
    """Issue 22: with scan times ``t [B, T]`` each step predicts over its own interval; the numpy IMM fed the same
    intervals agrees. The scans are 1 s trajectories kept at irregular gaps of 1-4 s (so that the motion between
    them is the truth's), their times from an epoch origin."""
    from immnet.data.spec import DataSpec

    full = pytest.importorskip("immnet.data.generate").generate(3, seed=709, spec=DataSpec(T=300, min_segment=60))
    gen = torch.Generator().manual_seed(3)
    keep = torch.randint(1, 5, (100,), generator=gen).cumsum(0)
    keep = keep[keep < 300]
    data = full.apply(lambda v: v[:, keep] if v.dim() >= 2 else v, batch_size=[3])
    data[keys.TIME] = 1.7e9 + 0.37 + keep.to(torch.float64).expand(3, -1).clone()
    if missed:
        data[keys.MEASUREMENTS][0, 30:33] = float("nan")
        data[keys.MEASUREMENTS][1, 1] = float("nan")  # the second detection after a missed scan
    out = IMMEKF(p_stay=0.97, sigma_q=0.3, r0=3.0, k0=2.0).track(data)
    assert not torch.equal(out[keys.STATE].nan_to_num(0), IMMEKF(p_stay=0.97, sigma_q=0.3, r0=3.0, k0=2.0).track(
        data.exclude(keys.TIME))[keys.STATE].nan_to_num(0))  # the times change the estimates
    for b in range(3):
        dts = np.diff(data[keys.TIME][b].numpy() - 1.7e9, prepend=np.nan)
        dts[0] = 1.0  # no interval before the first scan (never used)
        states, probs = _reference(data[keys.MEASUREMENTS][b].numpy(), 0.97, 0.3, 3.0, 2.0, dt=dts)
        np.testing.assert_allclose(out[keys.STATE][b].numpy(), states, rtol=1e-7, atol=1e-5)
        np.testing.assert_allclose(out[keys.MODE_PROBS][b].numpy(), probs, rtol=1e-6, atol=1e-6)


def test_imm_ekf_is_between_the_bound_and_the_measurements(data):
    data = pytest.importorskip("immnet.data.generate").generate(60, seed=708)
    truth = data[keys.STATES]
    ekf = rmse(position_error(build_method("imm-ekf").track(data)[keys.STATE], truth))["avg"]
    bound = rmse(position_error(ClairvoyantKF().track(data)[keys.STATE], truth))["avg"]
    raw = rmse(position_error(data[keys.MEASUREMENTS].repeat_interleave(3, dim=-1), truth))["avg"]
    assert bound < ekf < 0.7 * raw
    assert (REPO_ROOT / "configs" / "methods" / "imm-ekf.yaml").exists()


def test_imm_ekf_keeps_finite_states_through_a_long_gap(data):
    data = data.clone()
    data[keys.MEASUREMENTS][1, 20:80] = float("nan")
    out = IMMEKF().track(data)
    assert torch.isfinite(out[keys.STATE]).all() and torch.isfinite(out[keys.MODE_PROBS]).all()
    np.testing.assert_allclose(out[keys.MODE_PROBS].sum(-1).numpy(), 1.0, atol=1e-12)


@pytest.mark.parametrize(
    "kwargs, words",
    [({"p_stay": 1.5}, "p_stay"), ({"rate_noise_deg": -1.0}, "rate_noise_deg"), ({"r": -1.0}, "r must"),
     ({"rate_noise_deg": "fast"}, "rate_noise_deg must be finite and >= 0, got 'fast'"),
     ({"sigma_q": float("nan")}, "sigma_q"), ({"sigma_q": [0.1, 0.2]}, "sigma_q must be one number"),
     ({"p_stay": [[0.9, 0.1], [0.1, 0.9]]}, "p_stay must be one number")],
)
def test_imm_ekf_rejects_bad_settings(kwargs, words):
    with pytest.raises(ValueError, match=words):
        IMMEKF(**kwargs)
