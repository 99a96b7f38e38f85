"""Motion models against closed forms and a fine-step integration of the turn ODE."""

import math

import pytest
import torch

from immnet.config import REPO_ROOT
from immnet.motion import (
    DEG,
    AdaptiveTurn,
    ConstantAcceleration,
    ConstantVelocity,
    CoordinatedTurn,
    ModelSet,
    Singer,
    ct_matrix,
    adaptive_ct_propagate,
    ct_propagate,
    noise_gain,
    process_noise,
    turn_rate_of,
)


def _state(lx=100.0, vx=120.0, ax=0.0, ly=-50.0, vy=80.0, ay=0.0, lz=3000.0, vz=2.0, az=0.0):
    return torch.tensor([lx, vx, ax, ly, vy, ay, lz, vz, az], dtype=torch.float64)


def test_ca_matches_closed_form_kinematics():
    x0 = _state(ax=1.5, ay=-0.7, az=0.2)
    dt, steps = 0.5, 37
    F = ConstantAcceleration().F(dt)
    x = x0.clone()
    for _ in range(steps):
        x = F @ x
    t = dt * steps
    for p, v, a in ((0, 1, 2), (3, 4, 5), (6, 7, 8)):
        l0, v0, a0 = x0[p].item(), x0[v].item(), x0[a].item()
        assert x[p].item() == pytest.approx(l0 + v0 * t + 0.5 * a0 * t * t, rel=1e-12)
        assert x[v].item() == pytest.approx(v0 + a0 * t, rel=1e-12)
        assert x[a].item() == pytest.approx(x0[a].item(), rel=1e-12)


def test_cv_zeroes_acceleration_and_moves_linearly():
    x = ConstantVelocity().F(2.0) @ _state(ax=3.0)
    assert x[2] == 0 and x[0] == 100.0 + 2 * 120.0 and x[6] == 3000.0 + 4.0


@pytest.mark.parametrize("w_deg", [-10.0, -3.0, 1.0, 8.0], ids=lambda w: f"w={w:+g}")
def test_ct_keeps_speed_and_matches_turn_ode(w_deg):
    w = w_deg * DEG
    dt, steps = 1.0, 50
    F = CoordinatedTurn(w_deg).F(dt)
    x = _state()
    speed0 = math.hypot(x[1], x[4])
    # reference: RK4 on d(l, v)/dt = (v, w J v), J = [[0, -1], [1, 0]], with 1000 substeps per step
    ref = [x[0].item(), x[3].item(), x[1].item(), x[4].item()]

    def f(s):
        return [s[2], s[3], -w * s[3], w * s[2]]

    def add(s, k, c):
        return [a + c * b for a, b in zip(s, k)]

    h = dt / 1000
    for _ in range(steps):
        x = F @ x
        for _ in range(1000):
            k1 = f(ref)
            k2 = f(add(ref, k1, h / 2))
            k3 = f(add(ref, k2, h / 2))
            k4 = f(add(ref, k3, h))
            ref = [r + h / 6 * (a + 2 * b + 2 * c + d) for r, a, b, c, d in zip(ref, k1, k2, k3, k4)]
        assert math.hypot(x[1], x[4]) == pytest.approx(speed0, rel=1e-12)
    assert torch.allclose(torch.stack([x[0], x[3], x[1], x[4]]), torch.tensor(ref, dtype=torch.float64), rtol=0, atol=1e-6)
    # centripetal acceleration: a = w x v, magnitude w * speed
    assert x[2].item() == pytest.approx(-w * x[4].item(), rel=1e-12)
    assert x[5].item() == pytest.approx(w * x[1].item(), rel=1e-12)
    # z axis is CV
    assert x[6].item() == pytest.approx(3000.0 + 2.0 * steps * dt)


def test_ct_batched_and_zero_rate_limit():
    w = torch.tensor([0.0, 1e-12, 0.1, -0.1])
    F = ct_matrix(w, 1.0)
    assert F.shape == (4, 9, 9)
    cv = ct_matrix(torch.tensor(0.0), 1.0)
    assert torch.allclose(F[0], cv) and torch.allclose(F[1], cv, atol=1e-10)
    assert torch.allclose(F[2], ct_matrix(0.1, 1.0)) and torch.allclose(F[3], ct_matrix(-0.1, 1.0))


def test_process_noise_forms():
    G = noise_gain(2.0)
    assert torch.equal(G[0:3, 0], torch.tensor([2.0, 2.0, 0.0], dtype=torch.float64))
    Q = process_noise(0.2, 2.0, "wiener")
    assert Q[2, 2].item() == pytest.approx(0.04)
    assert torch.allclose(Q, Q.T)
    assert process_noise(torch.tensor([0.1, 1.0]), 1.0).shape == (2, 9, 9)
    with pytest.raises(ValueError, match="non-negative"):
        process_noise(-1.0, 1.0)


@pytest.mark.parametrize("name,n", [("imm3", 3), ("imm4", 4), ("imm4-adaptive", 4), ("imm6", 6)])
def test_model_sets_load_from_yaml(name, n):
    ms = ModelSet.from_config(REPO_ROOT / "configs" / "model_sets" / f"{name}.yaml")
    assert len(ms) == n and ms.F(1.0).shape == (n, 9, 9) and ms.Q(0.2).shape == (n, 9, 9)
    assert set(ms.modes.tolist()) <= {0, 1, 2, 3}


def test_model_set_errors():
    with pytest.raises(ValueError, match="at least one"):
        ModelSet([])
    with pytest.raises(ValueError, match="unknown class_path"):
        ModelSet.from_config([{"class_path": "immnet.motion.Nope"}])
    with pytest.raises(ValueError, match="non-zero"):
        CoordinatedTurn(0.0)
    with pytest.raises(ValueError, match="ct\\+3 appears more than once"):
        ModelSet([ConstantVelocity(), CoordinatedTurn(3.0), CoordinatedTurn(3.0)])


def test_turn_experts_of_one_sign_keep_distinct_names():
    slow, fast = AdaptiveTurn(3.0, 1.0, 10.0), AdaptiveTurn(7.0, 5.0, 10.0)
    ms = ModelSet([ConstantVelocity(), AdaptiveTurn(5.0), slow, fast, AdaptiveTurn(-5.0)])
    assert ms.names == ["cv", "ct+adaptive", "ct+adaptive1-10@3", "ct+adaptive5-10@7", "ct-adaptive"]
    assert ms.modes.tolist() == [0, 2, 2, 2, 3]


def test_ct_propagate_equals_the_transition_matrix():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(64, 9, dtype=torch.float64, generator=g) * 100.0
    w = (torch.rand(64, dtype=torch.float64, generator=g) - 0.5) * 0.5
    w[:3] = 0.0  # the w -> 0 limit
    for dt in (1.0, 0.4):
        expected = (ct_matrix(w, dt) @ x.unsqueeze(-1)).squeeze(-1)
        torch.testing.assert_close(ct_propagate(x, w, dt), expected, rtol=1e-12, atol=1e-9)


def test_turn_rate_of_a_coordinated_turn_is_its_rate():
    """After one CT step the acceleration is centripetal, ``a = w x v``: the rate is recovered."""
    for w_deg in (1.0, 4.5, -7.0, 10.0):
        x = ct_matrix(w_deg * DEG, 1.0) @ _state()
        assert turn_rate_of(x).item() == pytest.approx(w_deg * DEG, rel=1e-12)
    assert turn_rate_of(_state()).item() == 0.0  # straight flight


@pytest.mark.parametrize("w_deg", [2.0, 9.0, -3.0])
def test_adaptive_turn_follows_the_state_within_its_bounds(w_deg):
    x = ct_matrix(w_deg * DEG, 1.0) @ _state()
    plus, minus = AdaptiveTurn(5.0), AdaptiveTurn(-5.0)
    own, other = (plus, minus) if w_deg > 0 else (minus, plus)

    def step(model, x):  # the model's map: adaptive_ct_propagate at its bounds, as IMMNet's predict stage applies it
        return adaptive_ct_propagate(x, *model.rate_bounds(), 1.0)

    torch.testing.assert_close(step(own, x), ct_matrix(w_deg * DEG, 1.0) @ x, rtol=1e-12, atol=1e-9)
    # the other sign is bounded to its slowest rate, 1 deg/s the other way
    edge = -1.0 if w_deg > 0 else 1.0
    torch.testing.assert_close(step(other, x), ct_matrix(edge * DEG, 1.0) @ x, rtol=1e-12, atol=1e-9)
    # faster than max_deg is clamped to max_deg
    fast = ct_matrix(math.copysign(15.0, w_deg) * DEG, 1.0) @ _state()
    torch.testing.assert_close(step(own, fast), ct_matrix(math.copysign(10.0, w_deg) * DEG, 1.0) @ fast, rtol=1e-12, atol=1e-9)
    assert own.mode == (2 if w_deg > 0 else 3) and own.state_dependent
    with pytest.raises(ValueError, match="min_deg"):
        AdaptiveTurn(5.0, min_deg=6.0)


def _singer_closed_form(tau, dt):
    """Singer's F block and Q / q in closed form (Singer, IEEE TAES 1970; Bar-Shalom, Li & Kirubarajan 8.2.3
    with q = 2 sigma_m^2 / tau), float64: an independent computation of what the matrix exponentials give."""
    b = 1.0 / tau
    e, e2 = math.exp(-b * dt), math.exp(-2 * b * dt)
    F = [[1, dt, (b * dt - 1 + e) / b**2], [0, 1, (1 - e) / b], [0, 0, e]]
    q11 = (1 - e2 + 2 * b * dt + 2 * b**3 * dt**3 / 3 - 2 * b**2 * dt**2 - 4 * b * dt * e) / (2 * b**5)
    q12 = (e2 + 1 - 2 * e + 2 * b * dt * e - 2 * b * dt + b**2 * dt**2) / (2 * b**4)
    q13 = (1 - e2 - 2 * b * dt * e) / (2 * b**3)
    q22 = (4 * e - 3 - e2 + 2 * b * dt) / (2 * b**3)
    q23 = (e2 + 1 - 2 * e) / (2 * b**2)
    q33 = (1 - e2) / (2 * b)
    Q = [[q11, q12, q13], [q12, q22, q23], [q13, q23, q33]]
    return torch.tensor(F, dtype=torch.float64), torch.tensor(Q, dtype=torch.float64)


def _singer_noise_quadrature(tau, dt, n=20000):
    """``Q / q = int_0^dt exp(A s) L L^T exp(A^T s) ds`` by Simpson's rule on the closed-form ``exp(A s)``."""
    s = torch.linspace(0, dt, n + 1, dtype=torch.float64)
    b = 1.0 / tau
    g = torch.stack([(b * s - 1 + torch.exp(-b * s)) / b**2, (1 - torch.exp(-b * s)) / b, torch.exp(-b * s)], -1)
    f = g[:, :, None] * g[:, None, :]  # exp(A s) L = the last column
    w = torch.ones(n + 1, dtype=torch.float64)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    return (w[:, None, None] * f).sum(0) * dt / (3 * n)


@pytest.mark.parametrize("tau,dt", [(5.0, 1.0), (20.0, 5.2), (2.0, 0.5), (2.0, 5.5), (0.5, 12.0)])
def test_singer_matches_its_closed_form(tau, dt):
    F, Q = _singer_closed_form(tau, dt)
    torch.testing.assert_close(Q, _singer_noise_quadrature(tau, dt), rtol=1e-8, atol=1e-12)
    model = Singer(tau=tau, vertical=0.5)
    for a, scale in ((0, 1.0), (1, 1.0), (2, 0.25)):  # the z axis's q scaled by vertical^2
        block = slice(3 * a, 3 * a + 3)
        torch.testing.assert_close(model.F(dt)[block, block], F, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(model.Q(0.7, dt)[block, block], 0.49 * scale * Q, rtol=1e-9, atol=1e-14)
    assert model.F(dt)[0, 3] == 0 and model.Q(0.7, dt)[2, 5] == 0  # the axes apart, as CV and CA


def test_singer_tends_to_the_ca_model_and_takes_one_interval_per_track():
    # tau -> inf: the acceleration no longer reverts; F and Q are the CA model's with continuous white jerk
    ca = ConstantAcceleration(noise="continuous")
    torch.testing.assert_close(Singer(tau=1e9).F(3.0), ca.F(3.0), rtol=0, atol=1e-8)
    torch.testing.assert_close(Singer(tau=1e9).Q(0.5, 3.0), ca.Q(0.5, 3.0), rtol=1e-6, atol=1e-12)
    # no cancellation where dt << tau (the closed form loses every digit of q11 there)
    tiny = Singer(tau=1e4).Q(1.0, 1e-3)[0, 0].item()
    assert tiny == pytest.approx(1e-15 / 20, rel=1e-6)
    # a batch of intervals is a batch of the single-interval matrices
    dts = torch.tensor([[1.0, 4.6], [5.5, 0.25]], dtype=torch.float64)
    model = Singer(tau=8.0)
    F, Q = model.F(dts), model.Q(0.3, dts)
    assert F.shape == Q.shape == (2, 2, 9, 9)
    for i in range(2):
        for j in range(2):
            torch.testing.assert_close(F[i, j], model.F(dts[i, j].item()), rtol=1e-12, atol=1e-14)
            torch.testing.assert_close(Q[i, j], model.Q(0.3, dts[i, j].item()), rtol=1e-12, atol=1e-16)
    # the stationary variance of the acceleration is q tau / 2 (the Gauss-Markov process's)
    assert model.Q(1.0, 1e4)[2, 2].item() == pytest.approx(8.0 / 2, rel=1e-9)
    # either side of dt = tau (Van Loan below, the closed form above) the same continuous function
    torch.testing.assert_close(model.Q(1.0, 8.0 - 1e-9), model.Q(1.0, 8.0 + 1e-9), rtol=1e-7, atol=0)


def test_singer_config_round_trip_and_refusals():
    models = ModelSet.from_config([{"class_path": "immnet.motion.Singer", "init_args": {"tau": 15, "vertical": 0.3}},
                                   {"class_path": "immnet.motion.ConstantVelocity"}])
    assert models.names == ["singer15", "cv"] and models[0] == Singer(15.0, 0.3)
    assert ModelSet.from_config(models.to_config()).names == models.names
    assert models.modes.tolist() == [1, 0]  # stands for CA, the data mode of a maneuver along a line
    for tau in (0, -1, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="correlation time tau"):
            Singer(tau=tau)
    with pytest.raises(ValueError, match="continuous"):
        process_noise(1.0, 1.0, "wiener", order=2, tau=5.0)
