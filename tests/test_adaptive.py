"""Adaptive process noise (immnet.imm.adaptive): the rule against a closed form, and the trackers on
data with five times 3D-LAST's process noise (docs/robustness.md, "sigma_q 1")."""

import math

import numpy as np
import pytest
import torch

from immnet import keys
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.filters.methods import build_method
from immnet.evaluation.metrics import per_trajectory_rmse, position_error
from immnet.imm.adaptive import AdaptiveNoise


def _expected_nis(q_f: float, q: float, r: float) -> float:
    """Steady-state E[nu^2 / S] of a scalar random-walk Kalman filter that assumes process noise ``q_f``
    on a walk of ``q`` (measurement noise ``r``): its prior variance ``P`` solves ``P^2 = q_f (P + r)``,
    ``K = P / (P + r)``; the actual prior error variance ``V = (K^2 r + q) / (1 - (1 - K)^2)``."""
    P = 0.5 * (q_f + math.sqrt(q_f * q_f + 4.0 * q_f * r))
    K = P / (P + r)
    V = (K * K * r + q) / (1.0 - (1.0 - K) ** 2)
    return (V + r) / (P + r)


def _fixed_point(q: float, r: float, target: float, q0: float) -> float:
    """The scale ``lambda`` at which E[NIS] = ``target`` (bisection on log lambda, float64)."""
    lo, hi = 0.0, math.log(1e4)
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if _expected_nis(q0 * math.exp(mid), q, r) > target:
            lo = mid
        else:
            hi = mid
    return math.exp(0.5 * (lo + hi))


@pytest.mark.parametrize("deadband", [0.0, 0.3])
def test_scale_converges_to_the_closed_form_fixed_point(deadband):
    """Issue 20, item 7: on a scalar random walk with 16 times the assumed process noise, the rule's scale settles
    where the closed-form steady state's E[NIS] is 1 + deadband: with no deadband the true ratio, 16."""
    q0, ratio, r = 0.1, 16.0, 4.0
    rule = AdaptiveNoise(rate=0.01, deadband=deadband, nis_clip=1e6, max_scale=100.0, dim=1)
    expected = _fixed_point(ratio * q0, r, 1.0 + deadband, q0)
    if deadband == 0.0:
        assert expected == pytest.approx(ratio, rel=1e-9)
    rng = np.random.default_rng(7)
    B, T = 400, 4000
    x = np.zeros(B)
    xh, P = np.zeros(B), np.full(B, r)
    log_scale = torch.zeros(B, dtype=torch.float64)
    kept = []
    for t in range(T):
        x = x + rng.normal(0.0, math.sqrt(ratio * q0), B)
        z = x + rng.normal(0.0, math.sqrt(r), B)
        Pp = P + float(q0) * np.exp(log_scale.numpy())
        S = Pp + r
        nu = z - xh
        log_scale = rule.update(log_scale, torch.from_numpy(nu * nu / S), torch.ones(B, dtype=torch.bool))
        K = Pp / S
        xh, P = xh + K * nu, (1.0 - K) * Pp
        if t >= T // 2:
            kept.append(log_scale.numpy().copy())
    estimate = float(np.exp(np.mean(kept)))
    assert estimate == pytest.approx(expected, rel=0.05)
    if deadband == 0.0:
        assert estimate == pytest.approx(ratio, rel=0.05)


def test_scale_stays_at_one_and_bounded():
    """The scale never leaves [1, max_scale], holds on missed scans, and does not grow on consistent innovations."""
    rule = AdaptiveNoise(max_scale=10.0)
    log_scale = torch.zeros(3, dtype=torch.float64)
    for _ in range(2000):
        nis = torch.tensor([3.0, 1e9, float("nan")], dtype=torch.float64)
        log_scale = rule.update(log_scale, nis, torch.tensor([True, True, True]))
    assert log_scale.tolist() == pytest.approx([0.0, math.log(10.0), 0.0])
    held = rule.update(log_scale, torch.full((3,), 1e9, dtype=torch.float64), torch.zeros(3, dtype=torch.bool))
    assert torch.equal(held, log_scale)
    with pytest.raises(ValueError, match="AdaptiveNoise"):
        AdaptiveNoise.from_config({"rat": 0.1})


@pytest.fixture(scope="module")
def high_process_noise():
    """16 trajectories with sigma_q = 1 m/s^2 (3D-LAST's: 0.2), as configs/data/ood/sigma-q.yaml."""
    data = generate(16, seed=2020, spec=DataSpec(T=400, sigma_q=1.0))
    per_track = {}
    with torch.no_grad():
        for name in ["measurements", "imm-ekf", "imm-ekf-adaptive", "immnet", "immnet-adaptive"]:
            state = build_method(name).track(data)[keys.STATE]
            per_track[name] = per_trajectory_rmse(position_error(state, data[keys.STATES])).mean(-1)
    return {k: float(v.mean()) for k, v in per_track.items()}, per_track


def test_immnet_adaptive_below_raw_with_five_times_the_process_noise(high_process_noise):
    """Issue 20, item 7: on sigma_q = 1 data IMMNet's filter experts with adaptive process noise beat the raw
    measurements (without it IMMNet, whose KalmanNet learned its noise at 0.2, is above them: 4.04 against
    3.98 m on 200 trajectories), are within 1.5x the best model-based IMM, and no track diverges."""
    avg, per_track = high_process_noise
    assert avg["immnet"] > avg["measurements"]  # the set shows the fault (3.68 against 3.65 m)
    assert avg["immnet-adaptive"] < 0.95 * avg["measurements"]  # 3.28 m
    assert avg["immnet-adaptive"] <= 1.5 * min(avg["imm-ekf"], avg["imm-ekf-adaptive"])
    assert float((per_track["immnet-adaptive"] / per_track["measurements"]).max()) < 3.0


def test_imm_ekf_adaptive_improves_the_baseline(high_process_noise):
    """The model-based IMM-EKF gets the same mechanism: adaptive, it beats its fixed-noise self and the raw
    measurements on sigma_q = 1 data."""
    avg, _ = high_process_noise
    assert avg["imm-ekf-adaptive"] < 0.95 * min(avg["imm-ekf"], avg["measurements"])  # 3.27 against 3.63 m


def test_track_adapt_option_matches_the_python_api(tmp_path, capsys):
    """``immnet track --adapt`` loads the shipped weights with adaptive process noise, as
    ``Tracker.pretrained(adapt=True)`` does; on sigma_q = 1 data it changes the estimates."""
    from immnet.cli import main
    from immnet.tracking.tracker import Tracker

    z = generate(3, seed=5, spec=DataSpec(T=120, min_segment=40, sigma_q=1.0))[keys.MEASUREMENTS].float().numpy()
    np.savez(tmp_path / "in.npz", measurements=z, dt=1.0)
    outs = {}
    for flag in ([], ["--adapt"]):
        assert main(["track", "--input", str(tmp_path / "in.npz"), "--output", str(tmp_path / "out.npz"), *flag]) == 0
        outs[bool(flag)] = np.load(tmp_path / "out.npz")["state"]
    api = Tracker.pretrained(adapt=True).track(torch.from_numpy(z))
    np.testing.assert_allclose(outs[True], api["state"].numpy(), rtol=1e-5, atol=1e-4)
    assert np.abs(outs[True] - outs[False]).max() > 0.1
    capsys.readouterr()
