"""Batched Kalman filter against filterpy.kalman.KalmanFilter, missed detections, float32."""

import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter

from immnet.filters import KalmanFilterTracker, initial_state, inv3, predict, update
from immnet.motion import ConstantAcceleration, ConstantVelocity, CoordinatedTurn, measurement_matrix

MODELS = {"cv": ConstantVelocity(), "ca": ConstantAcceleration(), "ct+7": CoordinatedTurn(7.0)}


def _track(model, T=40, B=3, r=3.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    F = model.F(1.0)
    x = torch.tensor([1000.0, 80.0, 0.5, -2000.0, 40.0, -0.3, 3000.0, 2.0, 0.0], dtype=torch.float64)
    xs = []
    for _ in range(T):
        x = F @ x + 0.2 * torch.randn(9, generator=g, dtype=torch.float64)
        xs.append(x)
    X = torch.stack(xs).expand(B, T, 9)
    return X, X[..., 0::3] + r * torch.randn(B, T, 3, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("name", list(MODELS), ids=list(MODELS))
def test_kf_equals_filterpy(name):
    model, r, sq = MODELS[name], 3.0, 0.7
    _, z = _track(model)
    F, Q, H = model.F(1.0), model.Q(sq, 1.0), measurement_matrix()
    x, P = initial_state(z, r)
    ours_x, ours_ll, fp_x, fp_ll = [], [], [], []
    kfs = []
    for b in range(z.shape[0]):
        kf = KalmanFilter(9, 3)
        kf.F, kf.Q, kf.H, kf.R = F.numpy(), Q.numpy(), H.numpy(), r * r * np.eye(3)
        kf.x, kf.P = x[b].numpy().copy(), P[b].numpy().copy()
        kfs.append(kf)
    for t in range(1, z.shape[1]):
        x, P = predict(x, P, F, Q)
        x, P, ll = update(x, P, z[:, t], None, torch.tensor(r * r, dtype=torch.float64))
        ours_x.append(x.clone()), ours_ll.append(ll)
        for kf, zb in zip(kfs, z[:, t].numpy()):
            kf.predict()
            kf.update(zb)
            fp_x.append(kf.x.copy()), fp_ll.append(kf.log_likelihood)
    ours = torch.stack(ours_x).reshape(-1, 9).numpy()
    np.testing.assert_allclose(ours, np.array(fp_x), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(torch.stack(ours_ll).reshape(-1).numpy(), np.array(fp_ll), rtol=1e-9)
    np.testing.assert_allclose(P[-1].numpy(), kfs[-1].P, rtol=1e-8, atol=1e-10)


def test_general_H_matches_position_fast_path():
    g = torch.Generator().manual_seed(1)
    A = torch.randn(5, 9, 9, generator=g, dtype=torch.float64)
    P = A @ A.transpose(-1, -2) + torch.eye(9, dtype=torch.float64)
    x = torch.randn(5, 9, generator=g, dtype=torch.float64)
    z = torch.randn(5, 3, generator=g, dtype=torch.float64)
    R = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0], dtype=torch.float64)
    fast = update(x, P, z, None, R)
    general = update(x, P, z, measurement_matrix(), R)
    for a, b in zip(fast, general):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)


def test_inv3_closed_form():
    A = torch.randn(100, 3, 3, dtype=torch.float64)
    S = A @ A.transpose(-1, -2) + 0.1 * torch.eye(3, dtype=torch.float64)
    inv, logdet = inv3(S)
    torch.testing.assert_close(inv, torch.linalg.inv(S))
    torch.testing.assert_close(logdet, torch.logdet(S))


def test_inv3_of_an_ill_conditioned_float32_covariance_follows_float64():
    """A turn expert's innovation covariance after a 10 s gap (the general network, float32): eigenvalues 2e3 to 1.2e8.
    The adjugate's determinant of these float32 numbers was 1.6e15 (the true one 8.7e14; in a batch it came out
    negative, a NaN likelihood); the L D L^T pivots give the log-determinant and the inverse of float64."""
    S = torch.tensor([[59602448.0, -56290604.0, -17484580.0], [-56290604.0, 53169048.0, 16514832.0],
                      [-17484582.0, 16514832.0, 5132000.5]])
    inv, logdet = inv3(S)
    S64 = S.double()
    assert abs(float(logdet) - float(torch.logdet(S64))) < 1e-3
    exact = torch.linalg.inv(S64)
    assert float((inv.double() - exact).abs().max() / exact.abs().max()) < 1e-2
    assert torch.equal(inv, inv.transpose(-1, -2))


def test_missed_measurement_is_predict_only():
    model = MODELS["ct+7"]
    X, z = _track(model)
    x, P = initial_state(z, 3.0)
    xp, Pp = predict(x, P, model.F(1.0), model.Q(0.5))
    zt = z[:, 1].clone()
    zt[1, 2] = float("nan")  # one component missing is a missed detection
    xu, Pu, ll = update(xp, Pp, zt, None, 9.0)
    assert torch.equal(xu[1], xp[1]) and torch.equal(Pu[1], Pp[1]) and ll[1] == 0
    assert not torch.equal(xu[0], xp[0]) and ll[0] != 0
    assert torch.isfinite(xu).all() and torch.isfinite(Pu).all()


def test_kf_tracker_float32_close_to_float64():
    from tensordict import TensorDict

    X, z = _track(MODELS["cv"], T=60)
    batch = TensorDict({"measurements": z}, batch_size=[z.shape[0]])
    s64 = KalmanFilterTracker(ConstantVelocity(), 3.0, 0.5).track(batch)["state"]
    s32 = KalmanFilterTracker({"class_path": "immnet.motion.ConstantVelocity"}, 3.0, 0.5, dtype="float32").track(batch)["state"]
    assert s32.dtype == torch.float32
    torch.testing.assert_close(s32[..., 0::3].double(), s64[..., 0::3], rtol=0, atol=0.05)
    torch.testing.assert_close(s32[..., 1::3].double(), s64[..., 1::3], rtol=0, atol=0.01)
