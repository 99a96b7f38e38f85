"""The batched IMM against FilterPy's IMMEstimator, step by step; missed detections; float32."""

import numpy as np
import pytest
import torch
from filterpy.kalman import IMMEstimator, KalmanFilter

from immnet.filters import imm_filter, initial_state, predict
from immnet.motion import ConstantAcceleration, ConstantVelocity, CoordinatedTurn, ModelSet, measurement_matrix

SETS = {
    "cv-ca": [ConstantVelocity(), ConstantAcceleration()],
    "cv-ca-ct+5": [ConstantVelocity(), ConstantAcceleration(), CoordinatedTurn(5.0)],
    "wienerCV-ca-ct+4-ct-9": [ConstantVelocity("wiener"), ConstantAcceleration(), CoordinatedTurn(4.0), CoordinatedTurn(-9.0)],
    "imm6": [ConstantVelocity(), ConstantAcceleration()] + [CoordinatedTurn(w) for w in (3.0, 8.0, -3.0, -8.0)],
}


def _problem(models, seed, B=3, T=60):
    """Random sigma_q, r, transition matrix, mu0 and a maneuvering track per batch entry."""
    g = torch.Generator().manual_seed(seed)
    ms = ModelSet(models)
    M = len(ms)
    sq = (0.1 + torch.rand(M, generator=g, dtype=torch.float64)).tolist()
    F, Q = ms.F(1.0), ms.Q(sq)
    Pi = torch.rand(M, M, generator=g, dtype=torch.float64) + 3 * torch.eye(M, dtype=torch.float64)
    Pi = Pi / Pi.sum(-1, keepdim=True)
    mu0 = torch.rand(M, generator=g, dtype=torch.float64) + 0.1
    mu0 = mu0 / mu0.sum()
    r = 2.0 + 3 * float(torch.rand(1, generator=g))
    truth = [CoordinatedTurn(6.0).F(1.0), ConstantAcceleration().F(1.0), ConstantVelocity().F(1.0)]
    zs = []
    for _ in range(B):
        x = torch.tensor([5e3, 150.0, 0.0, -8e3, -90.0, 0.0, 4e3, 3.0, 0.0], dtype=torch.float64)
        x[2::3] = torch.randn(3, generator=g, dtype=torch.float64)
        xs = []
        for t in range(T):
            x = truth[(t // 20) % 3] @ x + 0.3 * torch.randn(9, generator=g, dtype=torch.float64)
            xs.append(x)
        zs.append(torch.stack(xs)[:, 0::3] + r * torch.randn(T, 3, generator=g, dtype=torch.float64))
    return F, Q, Pi, mu0, r, torch.stack(zs)


def _filterpy_imm(F, Q, Pi, mu0, r, x0, P0, z):
    """FilterPy's IMMEstimator over one track; a NaN row is a missed detection (predict only, mu = cbar)."""
    filters = []
    for Fm, Qm in zip(F.numpy(), Q.numpy()):
        kf = KalmanFilter(9, 3)
        kf.F, kf.Q, kf.H, kf.R = Fm, Qm, measurement_matrix().numpy(), r * r * np.eye(3)
        kf.x, kf.P = x0.copy(), P0.copy()
        filters.append(kf)
    imm = IMMEstimator(filters, mu0.numpy(), Pi.numpy())
    xs, mus = [imm.x.copy()], [imm.mu.copy()]
    for zt in z[1:]:
        imm.predict()
        if np.isnan(zt).any():
            imm.mu = imm.cbar.copy()
            imm._compute_mixing_probabilities()
            imm._compute_state_estimate()
        else:
            imm.update(zt)
        xs.append(imm.x.copy()), mus.append(imm.mu.copy())
    return np.array(xs), np.array(mus)


@pytest.mark.parametrize("missed", [False, True], ids=["all-detected", "missed"])
@pytest.mark.parametrize("set_name", list(SETS), ids=list(SETS))
def test_imm_equals_filterpy(set_name, missed):
    F, Q, Pi, mu0, r, z = _problem(SETS[set_name], seed=len(set_name) + missed)
    if missed:
        z[0, 5:9] = float("nan")
        z[1, 30, 1] = float("nan")
    x0, P0 = initial_state(z, r)
    states, probs, experts = imm_filter(z, x0, P0, F, Q, torch.tensor(r * r, dtype=torch.float64), Pi, mu0, True)
    for b in range(z.shape[0]):
        xs, mus = _filterpy_imm(F, Q, Pi, mu0, r, x0[b].numpy(), P0[b].numpy(), z[b].numpy())
        np.testing.assert_allclose(states[b].numpy(), xs, rtol=1e-9, atol=1e-9 * np.abs(xs).max())
        np.testing.assert_allclose(probs[b].numpy(), mus, rtol=1e-9, atol=1e-12)
    assert torch.isfinite(states).all() and torch.isfinite(experts).all()


def test_missed_detection_is_predict_only():
    F, Q, Pi, mu0, r, z = _problem(SETS["cv-ca-ct+5"], seed=3, T=12)
    z[:, 6] = float("nan")
    R = torch.tensor(r * r, dtype=torch.float64)
    x0, P0 = initial_state(z, r)
    before = imm_filter(z[:, :6], x0, P0, F, Q, R, Pi, mu0, True)
    after = imm_filter(z[:, :7], x0, P0, F, Q, R, Pi, mu0, True)
    # Expert j's estimate at the missed step is the prediction of its mixed prior; probabilities are cbar.
    mu = before[1][:, -1]
    cbar = mu @ Pi
    torch.testing.assert_close(after[1][:, -1], cbar, rtol=1e-12, atol=1e-15)
    w = Pi * mu[:, :, None] / cbar[:, None, :]
    x_mixed = torch.einsum("bij,bid->bjd", w, before[2][:, -1])
    x_pred, _ = predict(x_mixed, torch.zeros(1, 9, 9, dtype=torch.float64), F, Q)
    torch.testing.assert_close(after[2][:, -1], x_pred, rtol=1e-12, atol=1e-9)
    assert torch.isfinite(after[0]).all()


def test_float32_close_to_float64():
    F, Q, Pi, mu0, r, z = _problem(SETS["imm6"], seed=5, B=4, T=80)
    x0, P0 = initial_state(z, r)
    s64, p64, _ = imm_filter(z, x0, P0, F, Q, torch.tensor(r * r, dtype=torch.float64), Pi, mu0)
    f = torch.float32
    s32, p32, _ = imm_filter(z.to(f), x0.to(f), P0.to(f), F.to(f), Q.to(f), torch.tensor(r * r, dtype=f), Pi.to(f), mu0.to(f))
    assert s32.dtype == f and torch.isfinite(s32).all()
    assert (s32[..., 0::3].double() - s64[..., 0::3]).abs().max() < 0.05  # metres, at ~10 km from the radar
    assert (s32[..., 1::3].double() - s64[..., 1::3]).abs().max() < 0.05  # m/s
    assert (p32.double() - p64).abs().max() < 1e-3


@pytest.mark.parametrize("B", [1, 400], ids=["one-track", "many-tracks"])
def test_prediction_of_shared_matrices_equals_each_product(B):
    """``predict`` with every track's filters sharing ``F [M, 9, 9]`` (one product per filter over the tracks,
    ``vec(P) (F (x) F)^T``) equals ``F_m P_bm F_m^T + Q_m`` of each track and filter, formed one by one in numpy."""
    from immnet.imm.kalman import predict

    g = torch.Generator().manual_seed(3)
    M = 3
    F = torch.randn(M, 9, 9, generator=g, dtype=torch.float64)
    Q = torch.randn(M, 9, 9, generator=g, dtype=torch.float64)
    x = torch.randn(B, M, 9, generator=g, dtype=torch.float64)
    A = torch.randn(B, M, 9, 9, generator=g, dtype=torch.float64)
    P = A @ A.mT
    xp, Pp = predict(x, P, F, Q)
    Fn, Qn, xn, Pn = F.numpy(), Q.numpy(), x.numpy(), P.numpy()
    for b in range(B):
        for m in range(M):
            np.testing.assert_allclose(xp[b, m].numpy(), Fn[m] @ xn[b, m], rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(Pp[b, m].numpy(), Fn[m] @ Pn[b, m] @ Fn[m].T + Qn[m], rtol=1e-12, atol=1e-11)


@pytest.mark.parametrize("set_name", list(SETS), ids=list(SETS))
def test_fused_step_equals_filterpy(set_name):
    """The batch-last step written for torch.compile (run eagerly here), with missed detections."""
    from immnet.filters.imm_fused import fused_step, imm_filter_fused

    F, Q, Pi, mu0, r, z = _problem(SETS[set_name], seed=7 + len(set_name))
    z[0, 5:9] = float("nan")
    z[2, 30, 1] = float("nan")
    x0, P0 = initial_state(z, r)
    R = torch.tensor(r * r, dtype=torch.float64)
    states, probs, experts = imm_filter_fused(z, x0, P0, F, Q, R, Pi, mu0, True, step=fused_step)
    core = imm_filter(z, x0, P0, F, Q, R, Pi, mu0, True)
    torch.testing.assert_close(experts, core[2], rtol=1e-9, atol=1e-7)
    for b in range(z.shape[0]):
        xs, mus = _filterpy_imm(F, Q, Pi, mu0, r, x0[b].numpy(), P0[b].numpy(), z[b].numpy())
        np.testing.assert_allclose(states[b].numpy(), xs, rtol=1e-9, atol=1e-9 * np.abs(xs).max())
        np.testing.assert_allclose(probs[b].numpy(), mus, rtol=1e-8, atol=1e-12)  # no update-time symmetrization


@pytest.mark.slow
@pytest.mark.parametrize("set_name", ["wienerCV-ca-ct+4-ct-9"], ids=["wienerCV-ca-ct+4-ct-9"])
def test_compiled_equals_general_step(set_name):
    """``imm_filter(compile=True)`` (inductor) equals the core's scan loop in float64, and its
    float32 stays near float64; several batch sizes through one compiled graph (dynamic batch)."""
    F, Q, Pi, mu0, r, z = _problem(SETS[set_name], seed=13, B=5, T=30)
    z[0, 5:9] = float("nan")
    z[3, 12, 2] = float("nan")
    R = torch.tensor(r * r, dtype=torch.float64)
    x0, P0 = initial_state(z, r)
    general = imm_filter(z, x0, P0, F, Q, R, Pi, mu0, True)
    for B in (1, 5, 3):
        compiled = imm_filter(z[:B], x0[:B], P0[:B], F, Q, R, Pi, mu0, True, compile=True)
        for a, b in zip(compiled, general):
            torch.testing.assert_close(a, b[:B], rtol=1e-9, atol=1e-7)
    f = torch.float32
    s32, p32, _ = imm_filter(z.to(f), x0.to(f), P0.to(f), F.to(f), Q.to(f), R.to(f), Pi.to(f), mu0.to(f), compile=True)
    assert s32.dtype == f and torch.isfinite(s32).all()
    assert (s32.double() - general[0]).abs()[..., 0::3].max() < 0.05
    assert (p32.double() - general[1]).abs().max() < 3e-3  # the eager float32 path: 1.0e-3 on this problem
