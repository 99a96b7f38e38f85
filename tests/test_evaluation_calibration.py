"""Covariance out and its calibration (``immnet.evaluation.calibration``): a Kalman filter told the true
linear-Gaussian model is consistent, so its 95 % ellipsoids hold the truth at 95 % of the scans (NEES is
chi-square with 3 degrees of freedom); a filter told a 4x too small process noise is overconfident."""

import pytest
import torch
from tensordict import TensorDict

from immnet import keys
from immnet.evaluation.calibration import chi2_3_cdf, coverage, position_nees
from immnet.filters import IMMTracker, KalmanFilterTracker
from immnet.filters.per_axis import PerAxisIMMTracker
from immnet.motion import ConstantAcceleration, ConstantVelocity, ModelSet


def _linear_gaussian(model, sigma_q: float, r: float, B: int = 400, T: int = 60, seed: int = 0) -> TensorDict:
    """Tracks that follow ``model``'s own F and Q exactly at irregular 0.5-5 s scans, measured with noise r."""
    g = torch.Generator().manual_seed(seed)
    dt = 0.5 + 4.5 * torch.rand(B, T, generator=g, dtype=torch.float64)
    x = torch.zeros(B, 9, dtype=torch.float64)
    x[:, 1::3] = 100 * torch.randn(B, 3, generator=g, dtype=torch.float64)
    states = torch.empty(B, T, 9, dtype=torch.float64)
    states[:, 0] = x
    for t in range(1, T):
        F, Q = model.F(dt[:, t]), model.Q(sigma_q, dt[:, t])
        L = torch.linalg.cholesky(Q + 1e-12 * torch.eye(9, dtype=torch.float64))
        x = (F @ x.unsqueeze(-1)).squeeze(-1) + (L @ torch.randn(B, 9, 1, generator=g, dtype=torch.float64)).squeeze(-1)
        states[:, t] = x
    z = states[..., 0::3] + r * torch.randn(B, T, 3, generator=g, dtype=torch.float64)
    t = torch.cumsum(dt, 1) - dt[:, :1]
    return TensorDict({keys.STATES: states, keys.MEASUREMENTS: z, keys.R: torch.full((B,), r, dtype=torch.float64),
                       keys.DT: torch.ones(B), keys.TIME: t}, batch_size=[B])


def _coverage(method, data) -> dict:
    out = method.track(data)
    nees = position_nees(out[keys.STATE], out[keys.STATE_COV], data[keys.STATES])
    mask = torch.zeros_like(nees, dtype=torch.bool)
    mask[:, 10:] = True  # past the start, whose zero-velocity prior is not the truth's
    return coverage(nees, mask)


def test_the_chi2_cdf_is_the_closed_form():
    x = torch.randn(400_000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1)).pow(2).sum(-1)
    for p in (0.5, 0.95):
        assert float((chi2_3_cdf(x) <= p).double().mean()) == pytest.approx(p, abs=3e-3)


@pytest.mark.parametrize("model", [ConstantVelocity(noise="continuous"), ConstantAcceleration(noise="continuous", vertical=0.3)],
                         ids=["cv", "ca"])
def test_a_filter_told_the_true_model_is_calibrated(model):
    data = _linear_gaussian(model, sigma_q=0.8, r=5.0)
    told = _coverage(KalmanFilterTracker(model, "data", 0.8, return_cov=True), data)
    assert told[0.95] == pytest.approx(0.95, abs=0.01) and told[0.5] == pytest.approx(0.5, abs=0.02)
    wrong = _coverage(KalmanFilterTracker(model, "data", 0.2, return_cov=True), data)
    assert wrong[0.95] < 0.93  # told too little process noise: its ellipsoids are too small


def test_the_imms_covariances_match_the_kalman_filter_with_one_model():
    """One model: the joint IMM's and the decoupled IMM's covariances are the Kalman filter's."""
    model = ConstantAcceleration(noise="continuous", vertical=0.5)
    data = _linear_gaussian(model, sigma_q=0.5, r=3.0, B=8, T=30, seed=2)
    kf = KalmanFilterTracker(model, "data", 0.5, return_cov=True).track(data)[keys.STATE_COV]
    joint = IMMTracker(ModelSet([model]), "data", 0.5, p_stay=1.0, return_cov=True).track(data)[keys.STATE_COV]
    axis = PerAxisIMMTracker(ModelSet([model]), "data", 0.5, p_stay=1.0, return_cov=True).track(data)[keys.STATE_COV]
    torch.testing.assert_close(joint, kf, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(axis, kf, rtol=1e-7, atol=1e-7)
    assert keys.STATE_COV not in KalmanFilterTracker(model, "data", 0.5).track(data).keys()
