"""Filter experts (immnet.stages.filtering): the turn-rate Jacobian against autograd, the noise
estimate against numpy, each expert with an untrained network against an independent float64
extended Kalman filter, and the tracker's contracts (gradients, missed detections, streaming)."""

import math

import numpy as np
import pytest
import torch

from immnet import keys
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.motion import ModelSet, ct_propagate, ct_rate_derivative, process_noise
from immnet.stages import IMMNet
from immnet.stages.filtering import FilterGain, KalmanNetFilterGain
from immnet.tracking.tracker import Tracker
from immnet.training import Stage2Module

ADAPTIVE = "configs/model_sets/imm4-adaptive.yaml"
FILTER = {"class_path": "immnet.stages.filtering.KalmanNetFilterGain"}
FIXED = {"class_path": "immnet.stages.filtering.FilterGain"}
UNTRAINED = {"class_path": "immnet.stages.filtering.KalmanNetFilterGain", "init_args": {"init_out_scale": 0.0}}


@pytest.fixture(scope="module")
def data():
    td = generate(6, seed=5, spec=DataSpec(T=80, min_segment=20))
    return td.apply(lambda v: v.float() if v.is_floating_point() else v)


def test_turn_rate_derivative_is_autograds():
    torch.manual_seed(0)
    x = torch.randn(7, 9, dtype=torch.float64) * torch.tensor([1e3, 200, 5] * 3, dtype=torch.float64)
    for w in (0.15, -0.02, 0.003):
        wt = torch.full((7,), w, dtype=torch.float64)
        auto = torch.autograd.functional.jacobian(lambda v: ct_propagate(x, v, 1.0), wt)  # [7, 9, 7]
        auto = torch.einsum("bib->bi", auto)
        torch.testing.assert_close(ct_rate_derivative(x, wt, 1.0), auto, rtol=1e-7, atol=1e-6)
    # at w -> 0 (the closed form's limits), a central difference of the map
    h = torch.full((7,), 1e-5, dtype=torch.float64)
    central = (ct_propagate(x, h, 1.0) - ct_propagate(x, -h, 1.0)) / 2e-5
    for w in (0.0, 1e-8):
        torch.testing.assert_close(ct_rate_derivative(x, torch.full((7,), w, dtype=torch.float64), 1.0), central, rtol=1e-5, atol=1e-4)


def test_predict_jacobian_is_autograds():
    """``J (P + d d^T) J^T`` with ``P = I`` and ``d = 0`` (fused = own) is ``J J^T`` of the prior map."""
    net = IMMNet(model_set=ADAPTIVE, gain=FILTER).double()
    torch.manual_seed(1)
    B, M = 3, 4
    x = torch.randn(B, M, 9, dtype=torch.float64) * torch.tensor([1e3, 200, 2] * 3, dtype=torch.float64)
    w = torch.tensor([0.0, 0.0, 0.05, -0.09], dtype=torch.float64).expand(B, M)
    td = net.initial_carry(B, experts_alone=True, dtype=torch.float64)
    td.set(keys.FUSED, x)
    td.set(keys.EXPERT_POST, x)
    td.set(keys.EXPERT_RATE, w)
    td.set(keys.EXPERT_AUG_COV, torch.eye(10, dtype=torch.float64).expand(B, M, 10, 10))
    out = net.predict(net.interact(td.clone()))
    JJt = out.get(keys.EXPERT_AUG_PRIOR_COV)

    def prior(y):  # y [B, M, 10] -> the prior [B, M, 10] (w carried)
        t = td.clone()
        t.set(keys.FUSED, y[..., :9])
        t.set(keys.EXPERT_POST, y[..., :9])
        t.set(keys.EXPERT_RATE, y[..., 9])
        o = net.predict(net.interact(t))
        return torch.cat([o.get(keys.EXPERT_PRIOR), o.get(keys.EXPERT_RATE).unsqueeze(-1)], -1)

    y = torch.cat([x, w.unsqueeze(-1)], -1)
    J = torch.autograd.functional.jacobian(prior, y)  # [B, M, 10, B, M, 10]
    for b in range(B):
        for m in range(M):
            Jbm = J[b, m, :, b, m, :]
            if m < 2:  # CV and CA carry no turn rate: their w row is zero
                Jbm[9] = 0.0
            torch.testing.assert_close(JJt[b, m], Jbm @ Jbm.T, rtol=1e-9, atol=1e-9)


def _r2_reference(z: np.ndarray, r0: float, k0: float) -> np.ndarray:
    """The running r^2 estimate at each scan, from altitude third differences of consecutive detections."""
    T = z.shape[0]
    out = np.empty(T)
    total, count = 0.0, 0
    for t in range(T):
        if t >= 3:
            d3 = z[t, 2] - 3 * z[t - 1, 2] + 3 * z[t - 2, 2] - z[t - 3, 2]
            if np.isfinite(d3):
                total += d3 * d3 / 20.0
                count += 1
        out[t] = (k0 * r0 * r0 + total) / (k0 + count)
    return out


def test_noise_estimate_is_the_running_mean_of_third_differences(data):
    net = IMMNet(model_set=ADAPTIVE, gain=FILTER).double()
    z = data[keys.MEASUREMENTS].double().clone()
    z[1, 30:33] = math.nan
    z[2, 1] = math.nan  # a missed second detection: its first and third scans are not consecutive
    carry = net.initial_carry(z.shape[0], dtype=torch.float64)
    r2 = []
    for t in range(z.shape[1]):
        carry = net.scan(carry, z[:, t])
        r2.append(carry.get(keys.NOISE_VAR))
    r2 = torch.stack(r2, 1).numpy()
    for b in range(z.shape[0]):
        ref = _r2_reference(z[b].numpy(), 4.0, 3.0)
        np.testing.assert_allclose(r2[b], ref, rtol=1e-10)
    # the estimate knows the noise: within 30 % of the true r^2 after 80 scans, from a prior of 4 m
    true = data[keys.R].double().numpy() ** 2
    assert np.all(np.abs(r2[[0, 3, 4, 5], -1] / true[[0, 3, 4, 5]] - 1) < 0.3)


def _ekf_alone(z, model, idx, r0=4.0, k0=3.0, noise=(0.2, 0.2, 0.01, 0.002, 1e-5), rate_std0=5.0):
    """An independent float64 extended Kalman filter of one expert, started from two detections:
    state ``[x, w]``, autograd Jacobians, the process noise built from ``process_noise`` and the
    same components, the running r^2 of ``_r2_reference``."""
    CA_ACC_VAR = DataSpec().ca_acc_var()

    B, T, _ = z.shape
    turn = model.state_dependent
    lo, hi = model.rate_bounds() if turn else (0.0, 0.0)
    if turn:  # the fast edge at an aircraft's 30 deg/s where the model's range ends before it
        lo, hi = (lo, max(hi, 30.0 * math.pi / 180)) if lo > 0 else (min(lo, -30.0 * math.pi / 180), hi)
    own_acc = (not turn) and bool(model.F(1.0)[2, 2] != 0)
    F = model.F(1.0)

    def f(y):
        x, w = y[:9], y[9]
        if turn:
            return torch.cat([ct_propagate(x, w, 1.0), w[None]])
        return torch.cat([F @ x, torch.zeros(1, dtype=y.dtype)])

    sv_h, sv_v, sa_h, sa_v, sw = noise
    Q = torch.zeros(10, 10, dtype=torch.float64)
    Qh = process_noise(sv_h, 1.0, "white")
    Qv = process_noise(sv_v, 1.0, "white")
    Q[:6, :6] = Qh[:6, :6]
    Q[6:9, 6:9] = Qv[6:9, 6:9]
    if own_acc:
        Q[2, 2] = Q[5, 5] = sa_h**2
        Q[8, 8] = sa_v**2
    if turn:
        Q[9, 9] = sw**2
    H = torch.zeros(3, 10, dtype=torch.float64)
    H[0, 0] = H[1, 3] = H[2, 6] = 1.0
    out = torch.empty(B, T, 9, dtype=torch.float64)
    for b in range(B):
        r2 = _r2_reference(z[b].numpy(), r0, k0)
        y = torch.zeros(10, dtype=torch.float64)
        y[[0, 3, 6]] = z[b, 0]
        out[b, 0] = y[:9]
        y[[0, 3, 6]] = z[b, 1]
        y[[1, 4, 7]] = z[b, 1] - z[b, 0]
        y[9] = model.turn_rate if turn else 0.0
        out[b, 1] = y[:9]
        # the start covariance uses the estimate known before scan 1 (the prior: no third difference yet)
        rs = r0 * r0
        P = torch.zeros(10, 10, dtype=torch.float64)
        for a in range(3):
            p, v, c = 3 * a, 3 * a + 1, 3 * a + 2
            P[p, p], P[v, v], P[p, v], P[v, p] = rs, 2 * rs, rs, rs
            P[c, c] = CA_ACC_VAR[a]
        P[9, 9] = (rate_std0 * math.pi / 180) ** 2 if turn else 0.0
        for t in range(2, T):
            if turn:
                y = y.clone()
                y[9] = y[9].clamp(lo, hi)
            J = torch.autograd.functional.jacobian(f, y)
            if not turn:
                J[9, 9] = 0.0
            y = f(y)
            P = J @ P @ J.T + Q
            S = H @ P @ H.T + r2[t] * torch.eye(3, dtype=torch.float64)
            K = torch.linalg.solve(S, H @ P).T
            y = y + K @ (z[b, t] - H @ y)
            if turn:
                y[9] = y[9].clamp(lo, hi)
            IKH = torch.eye(10, dtype=torch.float64) - K @ H
            P = IKH @ P @ IKH.T + r2[t] * K @ K.T
            out[b, t] = y[:9]
    return out


@pytest.mark.parametrize("gain", [UNTRAINED, FIXED], ids=["kalmannet-at-zero", "fixed-noise"])
@pytest.mark.parametrize("idx", [0, 1, 2, 3])
def test_untrained_filter_expert_alone_is_an_extended_kalman_filter(data, idx, gain):
    """With the network's output at zero (no learned noise scale, no correction), or no network
    (``FilterGain``), expert ``idx`` alone on its data is the EKF of its own model, scan by scan
    (float64)."""
    net = IMMNet(model_set=ADAPTIVE, gain=gain).double()
    z = data[keys.MEASUREMENTS].double()[:3]
    M = net.n_experts
    out, _ = net.rollout(z.unsqueeze(1).expand(-1, M, -1, -1), experts_alone=True)
    ref = _ekf_alone(z, ModelSet.from_config(ADAPTIVE)[idx], idx)
    torch.testing.assert_close(out[keys.STATE][:, :, idx], ref, rtol=1e-6, atol=1e-6)


def test_gradients_reach_every_parameter_in_stage_2_with_filter_experts(data):
    module = Stage2Module(net={"model_set": ADAPTIVE, "gain": FILTER}, expert_weight=0.3)
    out, _ = module.net.rollout(data[keys.MEASUREMENTS][:, :30])
    batch = data.apply(lambda v: v[:, :30] if v.dim() >= 2 else v)
    module.losses(out, batch)[0].backward()
    dead = [n for n, p in module.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all() or p.grad.abs().sum() == 0]
    assert not dead, f"no gradient for {dead}"


RECIPE_NET = {  # the quick and pretrained recipes' model: the IMM interaction, the Bayes-corrected classifier
    "gain": {**FILTER, "init_args": {"interaction": "imm"}},
    "classifier": {"class_path": "immnet.stages.BayesTransformerClassifier"},
}


def test_gradients_reach_every_parameter_in_stage_2_with_the_recipes_model(data):
    """Through the IMM interaction and the Bayes-corrected classifier; its head's last layer starts at
    zero (no gradient behind it until the first step), so it is nudged off zero as a first step would."""
    module = Stage2Module(net={"model_set": ADAPTIVE, **RECIPE_NET}, expert_weight=0.3)
    with torch.no_grad():
        module.net.classify.head[-1].weight.normal_(0.0, 1e-3)
    out, _ = module.net.rollout(data[keys.MEASUREMENTS][:, :30])
    batch = data.apply(lambda v: v[:, :30] if v.dim() >= 2 else v)
    module.losses(out, batch)[0].backward()
    dead = [n for n, p in module.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all() or p.grad.abs().sum() == 0]
    assert not dead, f"no gradient for {dead}"


@pytest.mark.parametrize("net_cfg", [{"gain": FILTER}, RECIPE_NET], ids=["fused-transformer", "imm-bayes-transformer"])
def test_filter_experts_coast_through_missed_detections_and_stream_as_they_roll_out(data, net_cfg):
    net = IMMNet(model_set=ADAPTIVE, **net_cfg)
    z = data[keys.MEASUREMENTS][:, :50].clone()
    z[:, 10:14] = math.nan
    z[0, 0] = math.nan
    z[1, 30:] = math.nan
    tracker = Tracker(net)
    batched = tracker.track(z)
    assert torch.isfinite(batched[keys.STATE][:, 1:]).all()
    assert torch.isnan(batched[keys.STATE][0, 0]).all()  # no detection yet: no estimate
    tracker.reset(z.shape[0])
    for t in range(z.shape[1]):
        step = tracker.step(z[:, t])
        torch.testing.assert_close(step.get(keys.FUSED), batched[keys.STATE][:, t], rtol=1e-5, atol=1e-4, equal_nan=True)


def test_filter_gain_refuses_bad_settings():
    with pytest.raises(ValueError, match="u_max"):
        KalmanNetFilterGain(ModelSet.from_config(ADAPTIVE), u_max=0.0)
    with pytest.raises(ValueError, match="noise_std"):
        KalmanNetFilterGain(ModelSet.from_config(ADAPTIVE), noise_std=(0.2, 0.2, 0.01))
    # the two gains share one list of filter options (_FilterExperts._init_filter); the oracles are FilterGain's
    with pytest.raises(ValueError, match="KalmanNetFilterGain takes no restart, turn_rate"):
        KalmanNetFilterGain(ModelSet.from_config(ADAPTIVE), turn_rate="data", restart="data")
    for gain in (FilterGain, KalmanNetFilterGain):
        with pytest.raises(TypeError, match="noise_sd"):
            gain(ModelSet.from_config(ADAPTIVE), noise_sd=(0.2,) * 5)



def test_filter_gain_refuses_settings_that_are_not_finite():
    """A NaN or infinite process-noise std, noise prior or start rate std is refused as a negative one is, not taken
    (a NaN noise_std made every entry of the process noise NaN: NaN times the zeros of its component)."""
    ms = ModelSet.from_config(ADAPTIVE)
    for std in ((math.nan, 0.2, 0.01, 0.002, 1e-5), (0.2, math.inf, 0.01, 0.002, 1e-5)):
        with pytest.raises(ValueError, match="noise_std needs 5 standard deviations >= 0"):
            FilterGain(ms, noise_std=std)
    for bad in ({"r0": math.inf}, {"k0": math.nan}, {"rate_std0_deg": math.inf}):
        with pytest.raises(ValueError, match="r0 and k0 must be > 0 and rate_std0_deg >= 0"):
            FilterGain(ms, **bad)

def test_bayes_mode_update_from_filter_experts_is_the_imm_mode_update(data):
    """``mu_t ∝ N(nu; 0, S) (Pi^T mu_{t-1})`` with each filter expert's own prior covariance and r^2
    estimate, recomputed in numpy from what the step wrote."""
    bayes = {"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"p_stay": 0.9, "from_experts": True}}
    net = IMMNet(model_set=ADAPTIVE, gain=FIXED, classifier=bayes).double()
    z = data[keys.MEASUREMENTS].double()
    M = net.n_experts
    Pi = np.full((M, M), 0.1 / (M - 1))
    np.fill_diagonal(Pi, 0.9)
    carry = net.initial_carry(z.shape[0], dtype=torch.float64)
    for t in range(z.shape[1]):
        prev = carry.get(keys.EXPERT_PROBS).numpy()
        carry = net.scan(carry, z[:, t])
        if t < 3:
            continue
        P = carry.get(keys.EXPERT_AUG_PRIOR_COV).numpy()[..., [0, 3, 6], :][..., [0, 3, 6]]
        S = P + carry.get(keys.NOISE_VAR).numpy()[:, None, None, None] * np.eye(3)
        nu = z[:, t].numpy()[:, None, :] - carry.get(keys.EXPERT_PRIOR).numpy()[..., [0, 3, 6]]
        maha = np.einsum("bmi,bmij,bmj->bm", nu, np.linalg.inv(S), nu)
        loglik = -0.5 * (maha + np.log(np.linalg.det(S)) + 3 * np.log(2 * np.pi))
        np.testing.assert_allclose(carry.get(keys.EXPERT_LOGLIK).numpy(), loglik, rtol=1e-8, atol=1e-8)
        logp = np.log(prev @ Pi) + loglik
        expected = np.exp(logp - logp.max(-1, keepdims=True))
        expected /= expected.sum(-1, keepdims=True)
        # rtol 1e-6: the module stores log(Pi) as computed in float32
        np.testing.assert_allclose(carry.get(keys.EXPERT_PROBS).numpy(), expected, rtol=1e-6, atol=1e-10)


def _mix_reference(y, P, mu, Pi, own_acc, turn_sign, bound=None, bound_rate=0.0, bound_var=0.0):
    """The IMM's mixing with the generator's onset priors, one track at a time in numpy. ``Pi`` is
    ``[M, M]`` or one per track ``[B, M, M]``; ``bound [B, M, M]``, where given, is the part of each
    transition that enters a turn at a range bound: a mixture component of its own, whose rate is
    ``turn_sign[j] * bound_rate`` with variance ``bound_var``."""
    acc_var = [(3.0**3 - 0.5**3) / (3.0 * 2.5) / 2.0] * 2 + [0.6**2 / 12.0]
    w_mean, w_var = 5.5 * math.pi / 180.0, (9.0 * math.pi / 180.0) ** 2 / 12.0
    B, M, _ = y.shape
    y0, P0 = np.zeros((B, M, 10)), np.zeros((B, M, 10, 10))
    Pis = np.broadcast_to(Pi, (B, M, M))
    for b in range(B):
        Pi = Pis[b]
        cbar = Pi.T @ mu[b]
        for j in range(M):
            parts = []
            for i in range(M):
                if bound is not None and bound[b, i, j] > 0:
                    yb, Pb = y[b, i].copy(), P[b, i].copy()
                    yb[9] = turn_sign[j] * bound_rate
                    Pb[9, :] = Pb[:, 9] = 0.0
                    Pb[9, 9] = bound_var
                    if i != j and own_acc[j]:
                        raise AssertionError("a bound turn enters a turn filter only")
                    parts.append((mu[b, i] * bound[b, i, j] / cbar[j], yb, Pb))
                scheduled = Pi[i, j] - (0.0 if bound is None else bound[b, i, j])
                yi, Pi_ = y[b, i].copy(), P[b, i].copy()
                if i != j and own_acc[j]:
                    for a, v in zip((2, 5, 8), acc_var):
                        yi[a] = 0.0
                        Pi_[a, :] = Pi_[:, a] = 0.0
                        Pi_[a, a] = v
                if i != j and turn_sign[j]:
                    yi[9] = turn_sign[j] * w_mean
                    Pi_[9, :] = Pi_[:, 9] = 0.0
                    Pi_[9, 9] = w_var
                parts.append((mu[b, i] * scheduled / cbar[j], yi, Pi_))
            y0[b, j] = sum(w * yi for w, yi, _ in parts)
            P0[b, j] = sum(w * (Pk + np.outer(yi - y0[b, j], yi - y0[b, j])) for w, yi, Pk in parts)
    return y0, P0


def test_imm_interaction_is_the_imm_mixing_with_onset_priors():
    from tensordict import TensorDict

    from immnet.stages.filtering import FilterInteraction

    ms = ModelSet.from_config(ADAPTIVE)  # CV, CA, CT+ (own rate), CT- (own rate)
    stage = FilterInteraction(ms, 1.0, interaction="imm", p_stay=0.97).double()
    g = torch.Generator().manual_seed(3)
    B, M = 5, 4
    A = torch.randn(B, M, 10, 10, generator=g, dtype=torch.float64)
    P = A @ A.transpose(-1, -2) + 0.1 * torch.eye(10, dtype=torch.float64)
    y = torch.randn(B, M, 10, generator=g, dtype=torch.float64) * 50
    mu = torch.softmax(torch.randn(B, M, generator=g, dtype=torch.float64) * 2, -1)
    td = TensorDict({keys.EXPERT_POST: y[..., :9], keys.EXPERT_RATE: y[..., 9], keys.EXPERT_AUG_COV: P,
                     keys.EXPERT_PROBS: mu, keys.FUSED: y[:, 0, :9]}, batch_size=[B])
    y0, P0 = stage._mix(td)
    Pi = np.full((M, M), 0.01)
    np.fill_diagonal(Pi, 0.97)
    ry0, rP0 = _mix_reference(y.numpy(), P.numpy(), mu.numpy(), Pi, [False, True, False, False], [0, 0, 1, -1])
    np.testing.assert_allclose(y0.numpy(), ry0, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(P0.numpy(), rP0, rtol=1e-10, atol=1e-8)
    with pytest.raises(ValueError, match="interaction"):
        FilterInteraction(ms, 1.0, interaction="mixed")


def test_guarded_interaction_is_the_imm_mixing_with_state_dependent_transitions_and_a_bound_turn_component():
    from tensordict import TensorDict

    from immnet.imm.guard import G_MAX, RangeGuard
    from immnet.stages.filtering import FilterInteraction

    ms = ModelSet.from_config(ADAPTIVE)
    guard = RangeGuard()
    stage = FilterInteraction(ms, 1.0, interaction="imm", p_stay=0.97, guard=True).double()
    g = torch.Generator().manual_seed(4)
    B, M = 8, 4
    A = torch.randn(B, M, 10, 10, generator=g, dtype=torch.float64)
    P = A @ A.transpose(-1, -2) + 0.1 * torch.eye(10, dtype=torch.float64)
    y = torch.randn(B, M, 10, generator=g, dtype=torch.float64)
    # tracks 0-1 beyond the outer bound flying out (one each way round), 2 within the inner flying in,
    # 3 in a turn just past the clear, 4-5 inside the region, 6-7 inside it at a speed bound: the filters'
    # estimates scatter around these
    base = [(34_000, 0, 150, 60), (0, 33_500, 40, 180), (3_000, 500, -120, 30), (0, 34_000, -110, -100),
            (20_000, 5_000, 100, 0), (10_000, -9_000, -50, 200), (15_000, 0, 0, 330), (0, 15_000, 41, 0)]
    for b, (lx, ly, vx, vy) in enumerate(base):
        y[b, :, [0, 3, 1, 4]] = torch.tensor([lx, ly, vx, vy], dtype=torch.float64) + 5 * y[b, :, [0, 3, 1, 4]]
    # track 6: the CA filter has just passed 330 m/s accelerating (at 331.5 after +2 m/s^2: 329.5 a scan ago);
    # track 7: it has just dropped below 40 m/s (39.5, decelerating at 1.5 m/s^2)
    y[6, 1, [1, 4, 2, 5]] = torch.tensor([0.0, 331.5, 0.0, 2.0], dtype=torch.float64)
    y[7, 1, [1, 4, 2, 5]] = torch.tensor([39.5, 0.0, -1.5, 0.0], dtype=torch.float64)
    y[:, :, 9] = torch.tensor([0.0, 0.0, 1.0, -1.0], dtype=torch.float64) * 8.0 * math.pi / 180 + 0.01 * y[:, :, 9]
    mu = torch.softmax(torch.randn(B, M, generator=g, dtype=torch.float64) * 2, -1)
    # a speed-bound turn entered on the last scan (track 5: 70 % of the CT+ filter's prior) clears to CV
    fresh = torch.zeros(B, M, dtype=torch.float64)
    fresh[5, 2] = 0.7
    td = TensorDict({keys.EXPERT_POST: y[..., :9], keys.EXPERT_RATE: y[..., 9], keys.EXPERT_AUG_COV: P,
                     keys.EXPERT_PROBS: mu, keys.FUSED: y[:, 0, :9], keys.GUARD_FRESH: fresh}, batch_size=[B])
    y0, P0 = stage._mix(td)
    # the transition matrix per track, from the guard's events of each filter's estimate
    pos, neg, clear, _ = (e.numpy() for e in guard.events(y[..., :9], y[..., 9], 1.0))

    def out_of_bounds(vx, vy, vz):  # the speed rules, softened by 1 m/s
        sig = lambda u: 1 / (1 + np.exp(-u))  # noqa: E731
        hs = np.hypot(vx, vy)
        return 1 - sig(hs - 40.0) * sig(330.0 - hs) * sig(25.0 - np.abs(vz))

    yn = y.numpy()
    now = out_of_bounds(yn[..., 1], yn[..., 4], yn[..., 7])
    before = out_of_bounds(yn[..., 1] - yn[..., 2], yn[..., 4] - yn[..., 5], yn[..., 7] - yn[..., 8])
    speed = np.clip((now - before) / np.maximum(1 - before, 1e-6), 0, 1) * np.array([0, 1, 0, 0])  # CA only
    assert speed[6:, 1].min() > 0.4 and speed[:6].max() < 1e-3, speed
    clear = np.minimum(clear + fresh.numpy(), 1.0) * np.array([0, 0, 1, 1])
    gsum = pos + neg + clear + speed
    assert gsum.max() > 0.9 and gsum[4].max() < 1e-6, "the tracks must both meet and miss the bounds"
    cap = np.minimum(1.0, G_MAX / np.maximum(gsum, 1e-300))  # no event is made certain
    pos, neg, clear, speed, gsum = pos * cap, neg * cap, clear * cap, speed * cap, gsum * cap
    Pi = np.full((M, M), 0.01)
    np.fill_diagonal(Pi, 0.97)
    Pi_b = np.zeros((B, M, M))
    bound = np.zeros((B, M, M))
    by_speed = np.zeros((B, M, M))
    for b in range(B):
        for i in range(M):
            Pi_b[b, i] = (1 - gsum[b, i]) * Pi[i]
            Pi_b[b, i, 2] += pos[b, i] + speed[b, i] / 2  # a speed-bound turn's sign is a coin flip
            Pi_b[b, i, 3] += neg[b, i] + speed[b, i] / 2
            Pi_b[b, i, 0] += clear[b, i]
            bound[b, i, 2], bound[b, i, 3] = pos[b, i] + speed[b, i] / 2, neg[b, i] + speed[b, i] / 2
            by_speed[b, i, 2] = by_speed[b, i, 3] = speed[b, i] / 2
    torch.testing.assert_close(td.get(keys.MODE_TRANSITION), torch.from_numpy(Pi_b), rtol=1e-10, atol=1e-12)
    assert Pi_b[5, 2, 0] > 0.69  # the fresh speed-bound turn clears
    # carried to the next scan: the share of each filter's mixed prior that entered at a speed bound
    cbar = np.einsum("bi,bij->bj", mu.numpy(), Pi_b)
    expect_fresh = np.einsum("bi,bij->bj", mu.numpy(), by_speed) / cbar
    np.testing.assert_allclose(td.get(keys.GUARD_FRESH).numpy(), expect_fresh, rtol=1e-10, atol=1e-14)
    assert expect_fresh[6:, 2:].min() > 0.01 and expect_fresh[:, :2].max() == 0
    ry0, rP0 = _mix_reference(y.numpy(), P.numpy(), mu.numpy(), Pi_b, [False, True, False, False], [0, 0, 1, -1],
                              bound=bound, bound_rate=8.0 * math.pi / 180, bound_var=(0.2 * math.pi / 180) ** 2)
    np.testing.assert_allclose(y0.numpy(), ry0, rtol=1e-9, atol=1e-8)
    np.testing.assert_allclose(P0.numpy(), rP0, rtol=1e-9, atol=1e-7)
    with pytest.raises(ValueError, match="interaction='imm'"):
        FilterInteraction(ms, 1.0, interaction="fused", guard=True)


IMM_EKF = ["imm-ekf", "imm-ekf-guard", "imm-ekf-guard-sticky", "imm-ekf-adaptive", "imm-ekf-guard-sticky-adaptive",
           "imm-ekf-general", "imm-ekf-general-4sets"]
LINEAR = ["imm-min", "imm-max", "imm-accurate", "imm-tuned", "real-imm", "real-imm-5s", "real-imm-7s", "real-imm-11s",
          "mtt-imm-5s", "real-ca", "real-ca-5s", "real-ca-7s", "real-ca-11s"]
PER_AXIS = ["real-imm-axis", "real-imm-axis-5s", "real-imm-axis-7s", "real-imm-axis-11s", "real-imm-singer",
            "real-imm-singer-5s", "real-imm-singer-7s", "real-imm-singer-11s"]
ORACLES = ["clairvoyant", "clairvoyant-switch"]  # tests/test_filters_clairvoyant.py
TOLD_COV = ["radar-imm-5s", "radar-imm-11s", "radar-imm-robust-5s", "radar-imm-robust-11s"]  # tests/test_told_noise.py
# track runs network(); tests/test_filters_per_axis.py
PER_CHANNEL = ["real-imm-channel", "real-imm-channel-5s", "real-imm-channel-7s", "real-imm-channel-11s"]


def test_every_model_based_method_of_the_registry_is_held_to_its_step_configuration():
    """Issue 21, item 1: every model-based method the registry holds (configs/methods, every class but the learned
    networks') is one of the methods the equality tests of its kind run (above and below, and the files named), and
    has a ``network()``: no method joins the registry without its IMMNet-with-nothing-learned configuration."""
    import yaml

    from immnet.config import resolve_path
    from immnet.filters.methods import BUILTIN, available_methods, build_method

    held = set(IMM_EKF + LINEAR + PER_AXIS + ORACLES + PER_CHANNEL + TOLD_COV)
    model_based = []
    for name in available_methods():
        if name in BUILTIN:  # the raw measurements: no filter
            continue
        config = yaml.safe_load(resolve_path(f"configs/methods/{name}.yaml").read_text())
        if config["class_path"].startswith("immnet.tracking."):  # a learned network (IMMNet's, KalmanNet's)
            continue
        model_based.append(name)
        assert name in held, f"{name}: a model-based method no equality test holds to its network()"
        assert isinstance(build_method(name).network(), IMMNet), name
    assert len(model_based) == len(held)


@pytest.mark.parametrize("method", IMM_EKF)
def test_each_model_based_imm_is_immnet_with_nothing_learned(method):
    """Issue 21, item 1: the model-based IMM that IMMNet is compared with is IMMNet with nothing learned: the
    registry's method, built from its YAML, equals an ``IMMNet`` of filter experts with their base noise
    (the method's sigma_q on the white acceleration, its rate_noise_deg on the turn rate) and the IMM's Bayesian mode update,
    p_stay, guard and adaptation as the YAML says, exactly: the same start, interaction, filters and mode update."""
    import yaml

    from immnet.config import resolve_path
    from immnet.filters.methods import build_method

    args = yaml.safe_load(resolve_path(f"configs/methods/{method}.yaml").read_text())["init_args"]
    data = generate(12, seed=8, spec=DataSpec(T=150, min_segment=40))
    data[keys.MEASUREMENTS][3, 40:45] = float("nan")
    gain = {"class_path": "immnet.stages.filtering.FilterGain", "init_args": {
        "noise_std": [args["sigma_q"], args["sigma_q"], 0.0, 0.0, args.get("rate_noise_deg", 0.0) * math.pi / 180],
        "interaction": "imm", "p_stay": args["p_stay"],
        "guard": args.get("guard"), "adapt": args.get("adapt")}}
    bayes = {"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"p_stay": args["p_stay"], "from_experts": True}}
    net = IMMNet(model_set=ADAPTIVE, gain=gain, classifier=bayes).double()
    with torch.no_grad():
        out, _ = net.rollout(data[keys.MEASUREMENTS].double())
    ours = build_method(method).track(data)
    torch.testing.assert_close(ours[keys.STATE], out[keys.STATE], rtol=0, atol=0)
    torch.testing.assert_close(ours[keys.MODE_PROBS], out[keys.ROLLOUT_EXPERT_PROBS], rtol=0, atol=0)


@pytest.mark.parametrize("method", LINEAR)
def test_each_linear_imm_is_immnet_with_nothing_learned(method):
    """Issue 21, item 1, for the paper's linear IMMs, IMM-Tuned, the real-flight IMMs and the real-flight CA Kalman
    filter (an IMM of one model): the registry's method equals its ``network()``,
    IMMNet's step with filter experts of the method's own motion models and process noise, its ``r``, the mix
    without onset priors, a start from the first detection and the Bayesian mode update; both against the
    core's scan loop (``imm_filter``), to FilterPy's criterion (1e-9 of the state's scale; the mode
    update's exponential makes float64 rounding of the two covariance forms, Joseph's and the standard one,
    reach 1e-7 m where r is 1 m, as between the core's two formulations). Missed detections inside the tracks and a
    track first detected at scan 3 (each starts there, nothing reported before); the real-flight IMMs (continuous white noise, a vertical factor per model) are told each track's r."""
    import yaml

    from immnet.config import resolve_path
    from immnet.filters.methods import build_method
    from immnet.filters.base import data_mode_probs
    from immnet.filters.imm import first_detection, imm_filter, initial_state

    args = yaml.safe_load(resolve_path(f"configs/methods/{method}.yaml").read_text())["init_args"]
    data = generate(12, seed=8, spec=DataSpec(T=150, min_segment=40))
    data[keys.MEASUREMENTS][3, 40:45] = float("nan")
    data[keys.MEASUREMENTS][5, 1] = float("nan")  # a missed detection right after the start
    data[keys.MEASUREMENTS][7, :3] = float("nan")  # a track first detected at scan 3
    z = data[keys.MEASUREMENTS].double()
    tracker = build_method(method)
    net = tracker.network()
    assert net.start_detections == 1 and not net.interact.onset and net.gain.model_noise is not None
    told = args["r"] == "data"
    r = data[keys.R].double() if told else float(args["r"])
    with torch.no_grad():
        out, _ = net.rollout(z, r=r if told else None)
    if hasattr(tracker, "matrices"):
        F, Q, Pi, mu0 = tracker.matrices(1.0)
    else:  # a Kalman filter: the IMM of one model
        F, Q = tracker.model.F(1.0)[None], tracker.model.Q(tracker.sigma_q, 1.0)[None]
        Pi, mu0 = torch.ones(1, 1, dtype=torch.float64), torch.ones(1, dtype=torch.float64)
    x0, P0 = initial_state(z, r)
    R = r * r if told else torch.tensor(r * r, dtype=torch.float64)
    core, probs, _ = imm_filter(z, x0, P0, F, Q, R, Pi, mu0, start=first_detection(z))
    ours = tracker.track(data)
    scale = core.abs().amax((1, 2), keepdim=True)  # each track's
    seen = ~torch.isnan(z[..., :1])  # from each track's first detection on
    seen = seen.cumsum(1) > 0
    assert torch.equal(torch.isnan(ours[keys.STATE]), ~seen.expand_as(core))  # nothing before the first detection
    for states in (out[keys.STATE], ours[keys.STATE]):
        assert ((states - core).abs() <= 1e-9 * scale)[seen.expand_as(states)].all()
    seen_probs = seen[..., 0]
    torch.testing.assert_close(data_mode_probs(out[keys.ROLLOUT_EXPERT_PROBS], net.model_set.modes)[seen_probs],
                               data_mode_probs(probs, net.model_set.modes)[seen_probs], rtol=0, atol=1e-6)
    if told:  # without the step's input r the told filter gain says what it needs
        with pytest.raises(ValueError, match="r='data'"):
            net.rollout(z[:, :3])
        # as a method of immnet evaluate (Tracker.track), told the data's r as the filter is
        from immnet.tracking.methods import IMMNetMethod
        from immnet.tracking.networks import frame_origin, to_local, to_world
        from immnet.tracking.tracker import Tracker

        method = IMMNetMethod.from_tracker(Tracker(net.float()))
        assert keys.R in method.needs
        got = method.track(data)[keys.STATE]
        origin = frame_origin(net, z)  # Tracker.track's frame: each track's first detection
        with torch.no_grad():
            ref, _ = net.rollout(to_local(z, origin), r=r.float())
        torch.testing.assert_close(got[seen_probs], to_world(ref[keys.STATE], origin)[seen_probs], rtol=0, atol=0)
        assert torch.isnan(got[~seen_probs]).all()


@pytest.mark.parametrize("method", PER_AXIS)
def test_the_decoupled_imm_is_immnet_with_modes_per_axis(method):
    """Issue 21, item 1, for the decoupled IMM (``real-imm-axis``: one IMM per axis over CV and CA, each track's r
    told): its ``network()``, IMMNet's step with modes per axis (``modes="axis"``: mode probabilities ``[B, 3, M]``, each
    axis's mix, likelihood and mode update, the fusion per axis) over 9-D filter experts, filters what the method
    filters (the core's ``run`` over ``3 B`` one-coordinate tracks) to FilterPy's criterion (1e-9 of the state's
    scale), its modes per axis and its covariance (the axes' blocks, 0 across) too, at 1 s and at irregular 4.5-5.5 s
    scans. A model set with a turn, a range guard or a classifier without modes per axis is refused."""
    from immnet.filters.methods import build_method
    from immnet.stages.network import IMMNet

    data = generate(12, seed=8, spec=DataSpec(T=150, min_segment=40))
    data[keys.MEASUREMENTS][3, 40:45] = float("nan")
    data[keys.MEASUREMENTS][5, 1] = float("nan")  # a missed detection right after the start
    data[keys.MEASUREMENTS][7, :3] = float("nan")  # a track first detected at scan 3
    seen = torch.ones(12, 150, dtype=torch.bool)
    seen[7, :3] = False
    gen = torch.Generator().manual_seed(3)
    t = torch.cat([torch.zeros(12, 1), (4.5 + torch.rand(12, 149, generator=gen)).cumsum(1)], 1).double()
    slow = data.clone()
    slow[keys.TIME] = t
    tracker = build_method(method)
    tracker.return_cov = True
    net = tracker.network()
    assert net.modes == "axis" and net.start_detections == 1 and not net.interact.onset
    r = data[keys.R].double()
    outs = []
    for batch in (data, slow):
        z = batch[keys.MEASUREMENTS].double()
        intervals = net.intervals_for(batch)
        assert (intervals is None) == (batch is data)
        with torch.no_grad():
            out, _ = net.rollout(z, r=r, intervals=None if intervals is None else intervals.double(), return_cov=True)
        ref = tracker.track(batch)
        scale = ref[keys.STATE].nan_to_num().abs().amax((1, 2), keepdim=True)
        assert torch.equal(torch.isnan(ref[keys.STATE][..., 0]), ~seen)  # nothing before the first detection
        assert ((out[keys.STATE] - ref[keys.STATE]).abs() <= 1e-9 * scale)[seen].all()
        assert out[keys.ROLLOUT_EXPERT_PROBS].shape == ref[keys.EXPERT_PROBS].shape == (12, 150, 3, len(tracker.model_set))
        torch.testing.assert_close(out[keys.ROLLOUT_EXPERT_PROBS][seen], ref[keys.EXPERT_PROBS][seen], rtol=0, atol=1e-6)
        cov = out[keys.STATE_COV]
        torch.testing.assert_close(cov[seen], ref[keys.STATE_COV][seen], rtol=1e-6, atol=1e-9)
        assert (cov[..., 0:3, 3:9] == 0).all() and (cov[..., 3:6, 6:9] == 0).all()
        outs.append(out)
    # one mode for the whole state is another tracker: the axes' modes are what the configuration changes
    joint = IMMNet(model_set=net.model_set_config["models"], gain=net.config["gain"], classifier=net.config["classifier"],
                   p_stay=0.98, start_detections=1).double()
    with torch.no_grad():
        other, _ = joint.rollout(data[keys.MEASUREMENTS].double(), r=r)
    assert (other[keys.STATE] - outs[0][keys.STATE]).abs().amax() > 1e-3
    gain, bayes = net.config["gain"], net.config["classifier"]
    with pytest.raises(ValueError, match="couple"):
        IMMNet(model_set="configs/model_sets/imm4.yaml", gain=gain, classifier=bayes, modes="axis")
    with pytest.raises(ValueError, match="guard"):
        IMMNet(model_set=net.model_set_config["models"], gain=gain, classifier=bayes, modes="axis", guard=True)
    with pytest.raises(ValueError, match="the gain immnet.stages.KalmanNetGain has none"):  # the paper's: no likelihood
        IMMNet(model_set=net.model_set_config["models"], gain={"class_path": "immnet.stages.KalmanNetGain"},
               classifier=bayes, modes="axis")


def test_the_shipped_real_flight_network_has_modes_per_axis():
    """The shipped real-flight network is modes per axis, in its saved configuration and as loaded."""
    from immnet.checkpoints import shipped
    from immnet.tracking.tracker import load_network, read_checkpoint

    assert read_checkpoint(shipped("real"))[0]["modes"] == "axis"
    assert load_network(shipped("real")).modes == "axis"


def test_a_trained_network_with_its_learned_parts_knocked_out_is_the_model_based_imm():
    """``IMMNet.knock_out`` (the real-flight ablations, docs/notebook/real-flights.md): the shipped network with
    KalmanNet's and the Transformer's corrections set to zero is IMMNet with nothing learned, the filter experts at the
    gain's base noise and the IMM's mode update, with the network's own p_stay and guard; one part alone changes the
    estimates."""
    from immnet.checkpoints import PRETRAINED
    from immnet.tracking.methods import IMMNetMethod
    from immnet.tracking.tracker import load_network

    data = generate(6, seed=8, spec=DataSpec(T=120, min_segment=30))
    z = data[keys.MEASUREMENTS].double()
    shipped = load_network(PRETRAINED).double()
    c = shipped.classify  # the shipped gain's noise_std is KalmanNetFilterGain's default
    gain = {"class_path": "immnet.stages.filtering.FilterGain", "init_args": {
        "noise_std": [0.2, 0.2, 0.01, 0.002, 1e-5], "interaction": "imm", "p_stay": shipped.interact.p_stay,
        "guard": shipped.interact.guard.to_config()}}
    bayes = {"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"p_stay": c.p_stay, "from_experts": True}}
    reference = IMMNet(model_set=ADAPTIVE, gain=gain, classifier=bayes).double()
    with torch.no_grad():
        ref, _ = reference.rollout(z)
        full, _ = shipped.rollout(z)
        out, _ = load_network(PRETRAINED).double().knock_out("gain", "classifier").rollout(z)
        gain_off, _ = load_network(PRETRAINED).double().knock_out("gain").rollout(z)
    # the same equations, summed in another order (P + 1 * Q, a zero gain correction added): float64 rounding
    torch.testing.assert_close(out[keys.STATE], ref[keys.STATE], rtol=1e-7, atol=1e-6)
    torch.testing.assert_close(out[keys.ROLLOUT_EXPERT_PROBS], ref[keys.ROLLOUT_EXPERT_PROBS], rtol=1e-6, atol=1e-7)
    for other in (full, gain_off):
        assert float((other[keys.STATE] - ref[keys.STATE]).abs().max()) > 1e-3
    assert float((gain_off[keys.STATE] - full[keys.STATE]).abs().max()) > 1e-3
    method = IMMNetMethod(knock_out=["gain", "classifier"])
    pos = [0, 3, 6]  # the method runs in float32: positions to a few centimetres
    torch.testing.assert_close(method.track(data)[keys.STATE][..., pos], ref[keys.STATE][..., pos], rtol=0, atol=0.05)
    with pytest.raises(ValueError, match="no learned part 'noise'"):
        load_network(PRETRAINED).knock_out("noise")


def test_experts_alone_start_from_their_own_posterior_with_either_interaction(data):
    z = data[keys.MEASUREMENTS][:, :40]
    outs = []
    for inter in ("fused", "imm"):
        torch.manual_seed(0)
        net = IMMNet(model_set=ADAPTIVE, gain={**FILTER, "init_args": {"interaction": inter}})
        with torch.no_grad():
            outs.append(net.rollout(z.unsqueeze(1).expand(-1, net.n_experts, -1, -1), experts_alone=True)[0][keys.STATE])
    torch.testing.assert_close(outs[0], outs[1], rtol=0, atol=0)


def test_bayes_transformer_classifier_starts_as_the_imm_mode_update(data):
    """Its Transformer's head starts at zero: untrained, it is ``BayesianModeUpdate(from_experts)``."""
    gain = {**FILTER, "init_args": {"interaction": "imm"}}
    probs = []
    for classifier in ({"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"p_stay": 0.99, "from_experts": True}},
                       {"class_path": "immnet.stages.BayesTransformerClassifier", "init_args": {"p_stay": 0.99}}):
        torch.manual_seed(0)
        net = IMMNet(model_set=ADAPTIVE, gain=gain, classifier=classifier).double()
        with torch.no_grad():
            probs.append(net.rollout(data[keys.MEASUREMENTS].double())[0][keys.ROLLOUT_EXPERT_PROBS])
    # atol 1e-6: BayesianModeUpdate keeps log(Pi) in float32
    torch.testing.assert_close(probs[1], probs[0], rtol=0, atol=1e-6)
    assert probs[0][:, 3:].std() > 0.01  # the probabilities move: the comparison is not between constants


@pytest.mark.parametrize("classifier", ["immnet.stages.BayesianModeUpdate", "immnet.stages.BayesTransformerClassifier"])
def test_bayes_mode_updates_predict_with_the_guarded_transitions(classifier):
    """With a guard, ``mu_t ∝ N(nu; 0, S) (Pi_t^T mu_{t-1})`` with the step's own transition matrix
    ``Pi_t`` (``("mode", "transition")``), not the classifier's fixed one; checked scan by scan in numpy
    on generated trajectories that meet the range bounds (the Transformer's correction starts at zero)."""
    data = generate(6, seed=31)
    gain = {"class_path": "immnet.stages.filtering.FilterGain", "init_args": {"interaction": "imm", "guard": True}}
    args = {"p_stay": 0.995} | ({"from_experts": True} if classifier.endswith("Update") else {})
    net = IMMNet(model_set=ADAPTIVE, gain=gain, classifier={"class_path": classifier, "init_args": args}).double()
    z = data[keys.MEASUREMENTS].double()
    carry = net.initial_carry(z.shape[0], dtype=torch.float64)
    moved = 0.0
    with torch.no_grad():
        for t in range(z.shape[1]):
            prev = carry.get(keys.EXPERT_PROBS).numpy()
            carry = net.scan(carry, z[:, t])
            if t < 3:
                continue
            Pi = carry.get(keys.MODE_TRANSITION).numpy()
            logp = np.log(np.einsum("bi,bij->bj", prev, Pi)) + carry.get(keys.EXPERT_LOGLIK).numpy()
            expected = np.exp(logp - logp.max(-1, keepdims=True))
            expected /= expected.sum(-1, keepdims=True)
            np.testing.assert_allclose(carry.get(keys.EXPERT_PROBS).numpy(), expected, rtol=1e-6, atol=1e-9)
            moved = max(moved, float(np.abs(Pi - np.diag([0.995] * 4) - (1 - np.eye(4)) * 0.005 / 3).max()))
    assert moved > 0.5, "the guard never fired: the check would not tell the transitions apart"


@pytest.mark.parametrize("adapt", [False, True], ids=["shipped", "adaptive-noise"])
def test_the_filter_experts_step_traces_as_one_graph_and_gives_the_eager_outputs(data, adapt):
    """Issue 21, item 1: the IMM core runs eager and under ``torch.compile`` through the same code. The step
    of the shipped weights (filter experts, the IMM interaction with the range guard, Bayes + Transformer)
    has no data-dependent branch, so dynamo traces it as one graph (``fullgraph=True``; the ``eager``
    backend runs the traced graph, so the check needs no C++ compiler), and the graph's outputs are the
    eager step's."""
    from immnet.tracking.tracker import PRETRAINED, load_network

    net = load_network(PRETRAINED, adapt=adapt or "checkpoint")
    z = data["measurements"]
    with torch.no_grad():
        carry = net.initial_carry(z.shape[0])
        for t in range(6):
            carry = net.scan(carry, z[:, t])
        td = carry.copy()
        td.set(keys.MEASUREMENT, z[:, 6])
        torch._dynamo.reset()
        traced = torch.compile(net.step, fullgraph=True, backend="eager")(td.copy())
        eager = net.step(td.copy())
    for key in eager.keys(True, True):
        torch.testing.assert_close(traced.get(key), eager.get(key), rtol=1e-6, atol=1e-6, msg=str(key))


def test_a_network_told_each_tracks_r_trains_and_validates_with_the_datas_r():
    """``FilterGain(r="data")`` / ``KalmanNetFilterGain(r="data")``: stage 2 trains and validates with the batch's
    ``r`` as the step's input (``IMMNet.told_r``); another ``r`` in the data gives another loss."""
    cfg = {"model_set": "configs/model_sets/imm3.yaml", "p_stay": 0.9,
           "gain": {"class_path": "immnet.stages.filtering.KalmanNetFilterGain", "init_args": {
               "interaction": "imm", "onset": False, "model_noise": 0.5, "r": "data"}},
           "classifier": {"class_path": "immnet.stages.BayesTransformerClassifier"}}
    torch.manual_seed(0)
    module = Stage2Module(net=cfg, tbptt=10)
    module.log = lambda *a, **k: None
    td = generate(4, seed=2, spec=DataSpec(T=20, min_segment=6))
    td = td.apply(lambda v: v.float() if v.is_floating_point() else v)
    with torch.no_grad():
        loss = module.losses(module.net.rollout(td[keys.MEASUREMENTS], r=module.net.told_r(td))[0], td)[0]
        other = td.clone()
        other[keys.R] = other[keys.R] * 3.0
        moved = module.losses(module.net.rollout(td[keys.MEASUREMENTS], r=module.net.told_r(other))[0], td)[0]
    assert torch.isfinite(loss) and not torch.isclose(loss, moved)
    opt = torch.optim.Adam(module.trainable_parameters(), 1e-4)
    module.optimizers = lambda: opt
    module.manual_backward = lambda value: value.backward()
    module.training_step(td, 0)  # the step's input r from the batch, through every TBPTT chunk
    module._evaluate(td, "val")
    with pytest.raises(ValueError, match="holds no 'r'"):
        module.net.told_r(td.exclude(keys.R))


def test_init_parameters_takes_another_networks_weights_and_keeps_the_configured_base():
    """``Stage2Module(init_parameters=...)`` (``recipes/real-imm-base.yaml``'s network): the learned parameters of
    another network of four filter experts (the shipped 3D-LAST weights here; the recipe's, their real-flight
    fine-tune), the buffers (the models' noise, the chain) as ``net`` builds them; a network whose parameters the
    file does not hold (three experts against four) is refused by name."""
    import copy

    import yaml

    from immnet.checkpoints import shipped
    from immnet.config import resolve_path
    from immnet.tracking.tracker import read_checkpoint

    net = yaml.safe_load(resolve_path("recipes/real-imm-base.yaml").read_text())["model"]["init_args"]["net"]
    module = Stage2Module(net=net, init_parameters=str(shipped("3dlast")))
    _, weights = read_checkpoint(shipped("3dlast"))
    for name, p in module.net.named_parameters():
        assert torch.equal(p, weights[name].to(p.dtype)), name
    fresh = IMMNet(**net["init_args"])
    for name, b in fresh.state_dict().items():
        if name not in dict(fresh.named_parameters()):
            assert torch.equal(module.net.state_dict()[name], b), name  # the configured base, not the file's
    assert not torch.equal(module.net.gain.Q_parts, weights["gain.Q_parts"].to(module.net.gain.Q_parts.dtype))
    three = copy.deepcopy(net["init_args"])
    three["model_set"], three["gain"]["init_args"]["model_noise"] = "configs/model_sets/imm3.yaml", 0.5
    with pytest.raises(ValueError, match="does not hold this IMMNet's parameters"):
        Stage2Module(net={"class_path": "immnet.stages.IMMNet", "init_args": three}, init_parameters=str(shipped("3dlast")))



def test_the_float32_covariance_update_keeps_a_prior_of_nine_orders_positive():
    """``FilterUpdate``'s Joseph update on a float32 prior whose variances span nine orders (a filter expert of the
    general network on a base of higher process noise, after scans of up to 12 s: eigenvalues -0.15 to 2.5e9, positive
    semi-definite to float32's rounding; ``tests/data/float32_update_case.json``). Expanded in float32 its terms'
    rounding gave a variance of -64 m^2 (a NaN track a scan later, whole training batches skipped); the update
    follows the float64 one of the same inputs, every variance positive."""
    import json
    from pathlib import Path

    from immnet.imm.kalman import joseph

    case = json.loads((Path(__file__).parent / "data" / "float32_update_case.json").read_text())
    P = torch.tensor(case["P"], dtype=torch.float32)[None, None]
    K = torch.tensor(case["K"], dtype=torch.float32)[None, None]
    r2 = torch.full((1, 1, 1, 1), case["r2"], dtype=torch.float32)
    post = joseph(P, K, r2)
    ref = joseph(P.double(), K.double(), r2.double())
    assert post.dtype == torch.float32
    var, var64 = torch.diagonal(post[0, 0])[:9].double(), torch.diagonal(ref[0, 0])[:9]
    assert bool((var > 0).all()), var
    torch.testing.assert_close(var, var64, rtol=1e-4, atol=1e-3)
    assert torch.equal(post, post.transpose(-1, -2))


def test_init_parameters_widens_a_network_without_the_interval_input():
    """``init_parameters`` from the 3D-LAST network (1 s, no interval input) into the general recipe's network on
    another base: each weight that reads the interval gets its column as zeros (as ``init_checkpoint`` widens), every
    other parameter is the file's, and the buffers are the configured base's."""
    import yaml

    from immnet.checkpoints import shipped
    from immnet.config import resolve_path
    from immnet.tracking.tracker import read_checkpoint

    net = yaml.safe_load(resolve_path("recipes/general.yaml").read_text())["model"]["init_args"]["net"]
    net["init_args"]["p_stay"] = 0.98
    net["init_args"]["gain"]["init_args"]["noise_std"] = [0.5, 0.5, 0.01, 0.002, 0.001745]
    module = Stage2Module(net=net, init_parameters=str(shipped("3dlast")))
    _, weights = read_checkpoint(shipped("3dlast"))
    columns = module.net.interval_columns()
    assert columns
    for name, p in module.net.named_parameters():
        w = weights[name].to(p.dtype)
        if name in columns and w.shape != p.shape:
            col = columns[name]
            assert torch.equal(p[..., col], torch.zeros_like(p[..., col])), name
            assert torch.equal(torch.cat([p[..., :col], p[..., col + 1:]], -1), w), name
        else:
            assert torch.equal(p, w), name
    assert module.net.gain.noise_var_std[0].item() == pytest.approx(0.25)


def test_experts_alone_take_huber_update_with_modes_per_group():
    """Stage 1 (experts alone) with Huber's update and modes per group carries no far plot between scans, as the
    joint update experts alone: every plot within ``k`` is the plain update exactly (Huber's weight 1), and a plot
    2 km off (hundreds of standard deviations) moves each expert less than the plain update lets it."""
    torch.manual_seed(0)
    t = torch.arange(30.0)
    truth = torch.stack([100 * t, 50 * t, 0 * t], -1)  # [T, 3]
    z = truth + 3 * torch.randn(2, 3, 30, 3)  # [B, M, T, 3]: each expert its own sequence

    def run(zz, **options):
        gain = {"class_path": "immnet.stages.filtering.FilterGain", "init_args": {"r": 4.0, **options}}
        net = IMMNet(model_set="configs/model_sets/imm3.yaml", gain=gain, modes="channel")
        return net.rollout(zz, experts_alone=True)[0]["state"]  # [B, T, M, 9]

    assert torch.equal(run(z, robust=100.0), run(z))
    far = z.clone()
    far[:, :, 15] += 2000.0
    error = lambda state: (state[:, 15, :, 0:7:3] - truth[15]).norm(dim=-1)  # noqa: E731
    assert bool((error(run(far, robust=3.0)) < 0.6 * error(run(far))).all())


@pytest.mark.parametrize("gain", ["FilterGain", "KalmanNetFilterGain"])
@pytest.mark.parametrize("modes", ["joint", "channel", "axis"])
@pytest.mark.parametrize("alone", [False, True], ids=["full", "experts-alone"])
def test_huber_update_with_k_beyond_every_plot_is_the_plain_update(gain, modes, alone):
    """Huber's weight is 1 for a plot within ``k`` standard deviations (``kalman.huber``'s closed form), so with ``k``
    beyond every plot the robust update is the plain one, to the bit: in every mode grouping, in the full step and
    experts alone (stage 1), with a missed scan and an irregular interval."""
    from immnet.motion import ConstantAcceleration, ConstantVelocity

    per_axis = ModelSet([ConstantVelocity(), ConstantAcceleration()])  # block diagonal per axis
    model_set = per_axis if modes == "axis" else "configs/model_sets/imm3.yaml"
    t = torch.arange(12.0)
    truth = torch.stack([100 * t, 50 * t, 0 * t], -1)

    def run(**options):
        torch.manual_seed(0)  # the same weights for both (the robust update adds none)
        init = {"r": 4.0, **options} | ({"interval_input": True} if gain == "KalmanNetFilterGain" else {})
        net = IMMNet(model_set=model_set, gain={"class_path": f"immnet.stages.filtering.{gain}", "init_args": init},
                     modes=modes)
        z = truth + 3 * torch.randn((2, net.n_experts, 12, 3) if alone else (2, 12, 3))
        z[..., 5, :] = float("nan")
        intervals = torch.ones(2, 12)
        intervals[:, 8] = 1.3
        return net.rollout(z, experts_alone=alone, intervals=intervals if gain == "KalmanNetFilterGain" else None)[0]

    plain, robust = run(), run(robust=1e6)
    assert torch.isfinite(plain["state"][:, -1]).all()
    assert torch.equal(plain["state"], robust["state"])
