"""The IMM core (immnet.imm) and the motion models it predicts with, on intervals that differ per track and scan."""

import numpy as np
import pytest
import torch
from filterpy.kalman import IMMEstimator, KalmanFilter

from immnet.filters import imm_filter, initial_state
from immnet.motion import (
    AdaptiveTurn, ConstantAcceleration, ConstantVelocity, CoordinatedTurn, ModelSet, ca_matrix, ct_matrix, ct_propagate,
    cv_matrix, measurement_matrix, noise_gain, process_noise,
)


def test_motion_models_take_one_interval_per_track():
    """Issue 21, item 2: a model's ``F``, ``Q`` and the turn's map take a tensor of intervals ``dt [B]`` and
    give each track the matrix of its own interval, exactly the one a float ``dt`` gives."""
    dt = torch.tensor([1.0, 4.5, 0.1, 5.5], dtype=torch.float64)
    w = torch.tensor([0.1, -0.05, 0.0, 0.17], dtype=torch.float64)
    x = torch.randn(4, 9, dtype=torch.float64) * 100
    for b in range(4):
        d = float(dt[b])
        assert torch.equal(cv_matrix(dt)[b], cv_matrix(d)) and torch.equal(ca_matrix(dt)[b], ca_matrix(d))
        assert torch.equal(ct_matrix(w, dt)[b], ct_matrix(w[b], d))
        for kind in ("white", "wiener"):
            assert torch.equal(process_noise(0.3, dt, kind)[b], process_noise(0.3, d, kind))
            assert torch.equal(noise_gain(dt, kind)[b], noise_gain(d, kind))
        torch.testing.assert_close(ct_propagate(x, w, dt)[b], ct_matrix(w[b], d) @ x[b], rtol=1e-12, atol=1e-9)
    # a CA step of 4.5 s moves the position by v dt + a dt^2 / 2 (the closed form)
    F = ca_matrix(dt)[1]
    assert float((F @ torch.tensor([0.0, 10.0, 2.0] * 3, dtype=torch.float64))[0]) == pytest.approx(10 * 4.5 + 2 * 4.5**2 / 2)
    ms = ModelSet([ConstantVelocity(), ConstantAcceleration(), CoordinatedTurn(5.0), AdaptiveTurn(-5.0)])
    assert ms.F(dt).shape == (4, 4, 9, 9) and ms.Q(0.2, dt).shape == (4, 4, 9, 9)
    assert torch.equal(ms.F(dt)[2], ms.F(0.1)) and torch.equal(ms.Q(0.2, dt)[3], ms.Q(0.2, 5.5))


def _filterpy_imm_varying(F, Q, Pi, mu0, r, x0, P0, z):
    """FilterPy's IMMEstimator over one track whose filters' F and Q change every scan (``F [T, M, 9, 9]``)."""
    filters = []
    for _ in range(F.shape[1]):
        kf = KalmanFilter(9, 3)
        kf.H, kf.R = measurement_matrix().numpy(), r * r * np.eye(3)
        kf.x, kf.P = x0.copy(), P0.copy()
        filters.append(kf)
    imm = IMMEstimator(filters, mu0.numpy(), Pi.numpy())
    xs, mus = [imm.x.copy()], [imm.mu.copy()]
    for t in range(1, len(z)):
        for m, kf in enumerate(filters):
            kf.F, kf.Q = F[t, m].numpy(), Q[t, m].numpy()
        imm.predict()
        if np.isnan(z[t]).any():
            imm.mu = imm.cbar.copy()
            imm._compute_mixing_probabilities()
            imm._compute_state_estimate()
        else:
            imm.update(z[t])
        xs.append(imm.x.copy()), mus.append(imm.mu.copy())
    return np.array(xs), np.array(mus)


def test_the_core_takes_an_interval_per_track_and_scan():
    """Issue 21, item 1: the IMM core takes each scan's interval per track (``dt [B, T]``: 0.5 to 6 s, a
    radar's 4.5-5.5 s scans among them) and equals FilterPy's IMM given the same F and Q per scan, with
    missed detections, to 1e-9."""
    g = torch.Generator().manual_seed(3)
    B, T = 3, 40
    ms = ModelSet([ConstantVelocity(), ConstantAcceleration(), CoordinatedTurn(4.0)])
    dt = 0.5 + 5.5 * torch.rand(B, T, generator=g, dtype=torch.float64)
    F, Q = ms.F(dt), ms.Q([0.3, 0.5, 0.2], dt)  # [B, T, M, 9, 9]: the interval before scan t
    Pi = torch.tensor([[0.9, 0.05, 0.05], [0.1, 0.85, 0.05], [0.1, 0.1, 0.8]], dtype=torch.float64)
    mu0 = torch.tensor([0.5, 0.3, 0.2], dtype=torch.float64)
    t_s = torch.cumsum(dt, 1)
    truth = torch.stack([5e3 + 150 * t_s, -8e3 - 90 * t_s + 0.5 * t_s**2 / 10, 4e3 + 3 * t_s], -1)
    r = 4.0
    z = truth + r * torch.randn(B, T, 3, generator=g, dtype=torch.float64)
    z[0, 5:8] = float("nan")
    z[2, 20, 1] = float("nan")
    x0, P0 = initial_state(z, r)
    states, probs, _ = imm_filter(z, x0, P0, F, Q, torch.tensor(r * r, dtype=torch.float64), Pi, mu0, True)
    for b in range(B):
        xs, mus = _filterpy_imm_varying(F[b], Q[b], Pi, mu0, r, x0[b].numpy(), P0[b].numpy(), z[b].numpy())
        np.testing.assert_allclose(states[b].numpy(), xs, rtol=1e-9, atol=1e-9 * np.abs(xs).max())
        np.testing.assert_allclose(probs[b].numpy(), mus, rtol=1e-9, atol=1e-12)


def test_the_imm_core_imports_nothing_of_the_data():
    """Issue 61: immnet/imm knows nothing of 3D-LAST; the range guard's bounds and the onset priors' statistics are
    arguments whose defaults, constants of immnet/imm, are 3D-LAST's ``DataSpec``'s."""
    import ast
    from pathlib import Path

    import immnet.imm
    from immnet.data.spec import DataSpec
    from immnet.imm import RangeGuard
    from immnet.imm.interaction import ONSET_ACC_VAR, ONSET_RATE_PRIOR_DEG

    for path in Path(immnet.imm.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [node.module] if isinstance(node, ast.ImportFrom) else [a.name for a in getattr(node, "names", [])]
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                assert not any(n and n.startswith("immnet.data") for n in names), (path.name, names)
    spec = DataSpec()
    assert RangeGuard() == RangeGuard(**spec.guard_bounds())
    assert ONSET_ACC_VAR == spec.ca_acc_var() and ONSET_RATE_PRIOR_DEG == spec.turn_rate_prior_deg()
    other = DataSpec(bound_range_outer=50_000.0, bound_clear_heading_deg=45.0)
    assert RangeGuard(**other.guard_bounds()).outer == 50_000.0
    assert RangeGuard(**other.guard_bounds()).clear_share == pytest.approx(2**-0.5)


def test_one_gaussian_loglik_one_3x3_solve_one_moment_match():
    """Issue 61: the core's Gaussian log-likelihood, 3x3 inverse and moment match against independent computations
    (torch.distributions, LAPACK, a loop over the mixture's components)."""
    from immnet.imm.interaction import combine, moment_match
    from immnet.imm.kalman import gaussian_loglik, group_loglik, inv3

    g = torch.Generator().manual_seed(61)
    A = torch.randn(5, 3, 3, generator=g, dtype=torch.float64)
    S = A @ A.mT + 0.5 * torch.eye(3, dtype=torch.float64)
    nu = torch.randn(5, 3, generator=g, dtype=torch.float64)
    Si, logdet = inv3(S)
    torch.testing.assert_close(Si, torch.linalg.inv(S), rtol=1e-10, atol=1e-12)
    maha = (nu * (Si @ nu[..., None])[..., 0]).sum(-1)
    want = torch.distributions.MultivariateNormal(torch.zeros(3, dtype=torch.float64), S).log_prob(nu)
    torch.testing.assert_close(gaussian_loglik(maha, logdet, 3), want, rtol=1e-12, atol=1e-12)
    pair = torch.distributions.MultivariateNormal(torch.zeros(2, dtype=torch.float64), S[:, :2, :2]).log_prob(nu[:, :2])
    one = torch.distributions.Normal(0.0, S[:, 2, 2].sqrt()).log_prob(nu[:, 2])
    torch.testing.assert_close(group_loglik(nu, S, [[0, 1], [2]]), torch.stack([pair, one], -1), rtol=1e-12, atol=1e-12)
    # a mixture of M = 3 Gaussians in n = 4 per batch entry
    mu = torch.softmax(torch.randn(2, 3, generator=g, dtype=torch.float64), -1)
    x = torch.randn(2, 3, 4, generator=g, dtype=torch.float64)
    B = torch.randn(2, 3, 4, 4, generator=g, dtype=torch.float64)
    P = B @ B.mT
    xf, Pf = combine(x, P, mu)
    for b in range(2):
        mean = sum(mu[b, j] * x[b, j] for j in range(3))
        cov = sum(mu[b, j] * (P[b, j] + torch.outer(x[b, j] - mean, x[b, j] - mean)) for j in range(3))
        torch.testing.assert_close(xf[b], mean, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(Pf[b], cov, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(moment_match(mu[..., None, None], x, xf, P), Pf, rtol=0, atol=0)


def test_onset_priors_follow_the_filters_device():
    """``mix`` and ``enter`` take ``onset_priors``' float64 CPU tensors to the filters' dtype and device: the
    clairvoyant bounds hand them to ``runner.run`` as built, which on a GPU combined CPU priors with the states. The
    meta device stands for a GPU here."""
    from immnet.imm.interaction import enter, mix, onset_priors

    onset = onset_priors([False, True, False], [False] * 3, [0.0] * 3, n=9)
    x = torch.zeros(2, 3, 9, device="meta", dtype=torch.float32)
    P = torch.zeros(2, 3, 9, 9, device="meta", dtype=torch.float32)
    w = torch.zeros(2, 3, 3, device="meta", dtype=torch.float32)
    for out in (mix(w, x, P, onset), enter(x, P, *onset)):
        assert all(v.device.type == "meta" and v.dtype == torch.float32 for v in out)
