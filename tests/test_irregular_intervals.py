"""The model-based methods at any scan interval (issue 22): a batch carrying ``t [B, T]``.

The Kalman filter, a linear IMM (IMM-Tuned) and the clairvoyant bound on irregular scans (0.5-6 s, a
radar's 4.5-5.5 s) equal FilterPy fed each step's F and Q, with missed detections; scan times on a grid of
``dt`` give, bitwise, what the same batch without ``t`` gives (the fixed-interval fast paths).
"""

import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter
from tensordict import TensorDict
from test_imm_core import _filterpy_imm_varying

from immnet import keys
from immnet.config import REPO_ROOT, build
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.data.times import scan_intervals
from immnet.filters import ClairvoyantKF, KalmanFilterTracker, SwitchClairvoyantKF, initial_state
from immnet.motion import CA, CT_POS, CV, ConstantAcceleration, ca_matrix, ct_matrix, cv_matrix, measurement_matrix, process_noise

SCANS = {"0.5-6 s": (0.5, 6.0), "4.5-5.5 s": (4.5, 5.5)}


def _irregular(lo: float, hi: float, seed: int, B: int = 4, T: int = 160) -> TensorDict:
    """Generated 3D-LAST tracks (their modes, turn rates and r; p_miss 0.05 and a gap of 4 scans) whose scans
    are stamped ``t`` at epoch times with intervals ``U[lo, hi]`` to 0.01 s, measured on a weaving path at
    those times (the filters' numbers against FilterPy's are tested, not a fit to the generated truth)."""
    data = generate(B, seed=seed, spec=DataSpec(T=T, p_miss=0.05))
    g = torch.Generator().manual_seed(seed)
    steps = torch.round((lo + (hi - lo) * torch.rand(B, T, generator=g, dtype=torch.float64)) * 100) / 100
    s = torch.cumsum(steps, 1)
    data[keys.TIME] = 1.7e9 + s
    path = torch.stack([5e3 + 150 * s + 3e3 * torch.sin(s / 90), -8e3 - 90 * s + 2e3 * torch.cos(s / 70), 4e3 + 3 * s], -1)
    missed = torch.isnan(data[keys.MEASUREMENTS]).any(-1, keepdim=True)
    z = path + data[keys.R][:, None, None] * torch.randn(B, T, 3, generator=g, dtype=torch.float64)
    data[keys.MEASUREMENTS] = z.masked_fill(missed, float("nan"))
    data[keys.MEASUREMENTS][1, 40:44] = float("nan")
    return data


def _close(ours: torch.Tensor, ref: np.ndarray) -> None:
    np.testing.assert_allclose(ours.numpy(), ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())


def _waiting(z: np.ndarray) -> np.ndarray:
    """Scans before a track's first detection (the methods report NaN there)."""
    return np.cumsum(~np.isnan(z).any(-1)) == 0


@pytest.mark.parametrize("scans", list(SCANS), ids=list(SCANS))
def test_kalman_filter_equals_filterpy(scans):
    data = _irregular(*SCANS[scans], seed=1)
    r, sq, model = 4.0, 0.7, ConstantAcceleration()
    state = KalmanFilterTracker(model, r, sq).track(data)[keys.STATE]
    dt = scan_intervals(data)
    assert not torch.equal(dt[:, 1:], dt[:, 1:2].expand_as(dt[:, 1:]))
    z = data[keys.MEASUREMENTS]
    x0, P0 = initial_state(z, r)
    for b in range(z.shape[0]):
        kf = KalmanFilter(9, 3)
        kf.H, kf.R, kf.x, kf.P = measurement_matrix().numpy(), r * r * np.eye(3), x0[b].numpy().copy(), P0[b].numpy().copy()
        xs = [kf.x.copy()]
        for t in range(1, z.shape[1]):
            kf.F, kf.Q = model.F(float(dt[b, t])).numpy(), model.Q(sq, float(dt[b, t])).numpy()
            kf.predict()
            if not np.isnan(z[b, t].numpy()).any():
                kf.update(z[b, t].numpy())
            xs.append(kf.x.copy())
        keep = ~_waiting(z[b].numpy())
        _close(state[b][keep], np.array(xs)[keep])


@pytest.mark.parametrize("scans", list(SCANS), ids=list(SCANS))
def test_imm_tuned_equals_filterpy(scans):
    """The IMM-Tuned registry method (imm6, per-model sigma_q) against FilterPy's IMMEstimator."""
    data = _irregular(*SCANS[scans], seed=2, B=3)
    imm = build(REPO_ROOT / "configs" / "methods" / "imm-tuned.yaml")
    imm.return_experts = True
    out = imm.track(data)
    dt = scan_intervals(data)
    F, Q, Pi, mu0 = imm.matrices(dt)  # [B, T, M, 9, 9], each track's interval before scan t
    z = data[keys.MEASUREMENTS]
    x0, P0 = initial_state(z, imm.r)
    for b in range(z.shape[0]):
        for t in (1, 50, 100):  # the matrices are the motion models' of that scan's interval
            d = float(dt[b, t])
            torch.testing.assert_close(F[b, t], imm.model_set.F(d), rtol=0, atol=0)
            torch.testing.assert_close(Q[b, t], imm.model_set.Q(imm.sigma_q, d), rtol=0, atol=0)
        xs, mus = _filterpy_imm_varying(F[b], Q[b], Pi, mu0, imm.r, x0[b].numpy(), P0[b].numpy(), z[b].numpy())
        keep = ~_waiting(z[b].numpy())
        _close(out[keys.STATE][b][keep], xs[keep])
        np.testing.assert_allclose(out[keys.EXPERT_PROBS][b][keep].numpy(), mus[keep], rtol=1e-9, atol=1e-12)


def _filterpy_clairvoyant(method: ClairvoyantKF, batch: TensorDict, b: int) -> np.ndarray:
    """The bound as one FilterPy KalmanFilter: at each scan the true mode's F (CT at the true rate) and the
    white-noise Q of that scan's interval; entering CA, the acceleration restarts at 0 with the draw's
    variance, uncorrelated (as the generator draws a new one)."""
    z, mode, w = batch[keys.MEASUREMENTS][b].numpy(), batch[keys.MODE][b], batch[keys.TURN_RATE][b]
    r, dt = float(batch[keys.R][b]), scan_intervals(batch)[b]
    x0, P0 = initial_state(batch[keys.MEASUREMENTS][b : b + 1], r)
    acc, var = [2, 5, 8], np.array(method.acc_var)
    kf = KalmanFilter(9, 3)
    kf.H, kf.R, kf.x, kf.P = measurement_matrix().numpy(), r * r * np.eye(3), x0[0].numpy().copy(), P0[0].numpy().copy()
    if int(mode[0]) == CA:
        kf.P[np.ix_(acc, acc)] = np.diag(var)
    xs = [kf.x.copy()]
    for t in range(1, len(z)):
        d, m = float(dt[t]), int(mode[t])
        if m == CA and int(mode[t - 1]) != CA:
            kf.x[acc] = 0.0
            kf.P[acc, :] = 0.0
            kf.P[:, acc] = 0.0
            kf.P[np.ix_(acc, acc)] = np.diag(var)
        F = cv_matrix(d) if m == CV else ca_matrix(d) if m == CA else ct_matrix(float(w[t]), d)
        kf.F, kf.Q = F.numpy(), process_noise(method.sigma_q, d, "white").numpy()
        kf.predict()
        if not np.isnan(z[t]).any():
            kf.update(z[t])
        xs.append(kf.x.copy())
    return np.array(xs)


@pytest.mark.parametrize("scans", list(SCANS), ids=list(SCANS))
def test_clairvoyant_equals_filterpy(scans):
    data = _irregular(*SCANS[scans], seed=3, B=4, T=200)
    assert {CV, CA, CT_POS} <= set(data[keys.MODE].unique().tolist())  # every kind of step and a CA onset
    bound = ClairvoyantKF()
    state = bound.track(data)[keys.STATE]
    for b in range(data.batch_size[0]):
        keep = ~_waiting(data[keys.MEASUREMENTS][b].numpy())
        _close(state[b][keep], _filterpy_clairvoyant(bound, data, b)[keep])


def test_switch_clairvoyant_told_the_turn_rate_is_the_bound_at_irregular_scans():
    """Where every turn flies at 6 deg/s and the rate prior is exactly that, the EKF of ``[x, w]`` equals the
    bound scan by scan at irregular intervals too (its Jacobians and Q of each scan's interval)."""
    data = generate(12, seed=7, spec=DataSpec(T=200, min_segment=40, p_miss=0.05, turn_rate_min_deg=6.0,
                                              turn_rate_max_deg=6.0, bound_turn_rate_deg=6.0))
    g = torch.Generator().manual_seed(8)
    data[keys.TIME] = torch.cumsum(0.5 + 5.5 * torch.rand(12, 200, generator=g, dtype=torch.float64), 1)
    bound = ClairvoyantKF().track(data)[keys.STATE]
    told = SwitchClairvoyantKF(turn_prior_deg=(6.0, 0.0)).track(data)[keys.STATE]
    torch.testing.assert_close(told, bound, rtol=1e-9, atol=1e-7)


@pytest.mark.parametrize("dt, origin", [(1.0, 1.7e9), (5.0, 0.0), (0.5, 12.0)], ids=["1s-epoch", "5s", "0.5s"])
def test_scan_times_on_the_grid_change_nothing(dt, origin):
    """``t = origin + k dt`` gives bitwise the output without ``t`` (the fast paths, F and Q built once)."""
    data = generate(6, seed=11, spec=DataSpec(T=150, dt=dt, p_miss=0.05))
    timed = data.clone()
    timed[keys.TIME] = origin + dt * torch.arange(150, dtype=torch.float64).expand(6, 150)
    methods = [KalmanFilterTracker(ConstantAcceleration(), 4.0, 0.5), build(REPO_ROOT / "configs" / "methods" / "imm-tuned.yaml"),
               ClairvoyantKF(), SwitchClairvoyantKF(), ClairvoyantKF(dtype="float32")]
    for method in methods:
        assert method.any_interval
        a, b = method.track(data), method.track(timed)
        for key in a.keys(include_nested=True, leaves_only=True):
            assert torch.equal(a[key].nan_to_num(-1.0), b[key].nan_to_num(-1.0)), (method.name, key)
