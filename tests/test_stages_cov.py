"""Issue 23, item 5: IMMNet's fused covariance. Where the experts carry a covariance (the recipes' filter
experts, the analytic gain) the fuse stage writes ``P_t = sum_i mu_i (P_i + (x_i - x)(x_i - x)^T)``; the
rollout, ``Tracker.track`` and ``Tracker.step`` give it; the paper's KalmanNet experts give none and say why.
With ``cov_consistency`` (the default network's) the reported covariance is that one times a running mean of the
experts' normalized innovation squared over 3, the estimate unchanged (docs/immnet.md, "Covariance consistency")."""

import math

import numpy as np
import pytest
import torch

from immnet import keys
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.stages import IMMNet
from immnet.tracking.networks import frame_origin, to_local, to_world
from immnet.tracking.tracker import Tracker

SCANS = (2, 9, 29)  # a second detection, early running, the last


@pytest.fixture(scope="module")
def tracker():
    return Tracker.pretrained("general")


@pytest.fixture(scope="module")
def z():
    """Six tracks of 30 scans with missed detections: track 0 starts at scan 4, track 1 misses its second scan."""
    data = generate(6, seed=11, spec=DataSpec(T=30, min_segment=10))
    z = data[keys.MEASUREMENTS].float().clone()
    z[torch.rand(z.shape[:2], generator=torch.Generator().manual_seed(2)) < 0.15] = math.nan
    z[0, :4] = math.nan
    z[0, 4:6] = data[keys.MEASUREMENTS][0, 4:6].float()
    z[1, 0] = data[keys.MEASUREMENTS][1, 0].float()
    z[1, 1] = math.nan
    return z


@pytest.fixture(scope="module")
def tracked(tracker, z):
    """``Tracker.track(z, return_cov=True)``: the rollout's outputs, NaN before each track's first detection."""
    return tracker.track(z, return_cov=True)


def _moment_matched(carry) -> torch.Tensor:
    """The fused covariance from the experts' outputs, in float64 and one expert at a time."""
    mu, post = carry.get(keys.EXPERT_PROBS).double(), carry.get(keys.EXPERT_POST).double()
    P = carry.get(keys.EXPERT_AUG_COV).double()[..., :9, :9]
    x = (mu.unsqueeze(-1) * post).sum(1)
    want = torch.zeros(x.shape[0], 9, 9, dtype=torch.float64)
    for i in range(mu.shape[1]):
        d = post[:, i] - x
        want += mu[:, i, None, None] * (P[:, i] + torch.einsum("bi,bj->bij", d, d))
    return want


def test_the_fused_covariance_is_the_moment_matched_mixture_of_the_experts(tracker, z, tracked):
    net = tracker.net
    assert net.has_cov and net.fuse.cov == keys.EXPERT_AUG_COV
    carry, states, covs = net.initial_carry(z.shape[0]), [], []
    origin = frame_origin(net, z)  # Tracker.track's frame: each track's first detection
    local = to_local(z, origin)
    with torch.no_grad():
        for t in range(z.shape[1]):
            carry = net.scan(carry, local[:, t])
            states.append(carry.get(keys.FUSED))
            covs.append(net.reported_cov(carry))
            if t in SCANS:
                want = _moment_matched(carry)
                got = carry.get(keys.FUSED_COV).double()
                torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5 * float(want.abs().amax()))
    started = ~torch.isnan(tracked[keys.STATE][..., 0])  # the rollout's, where Tracker.track reports it
    assert torch.equal(tracked[keys.STATE_COV][started], torch.stack(covs, 1)[started])
    assert torch.equal(tracked[keys.STATE][started], to_world(torch.stack(states, 1), origin)[started])


def test_a_starting_track_has_its_start_covariance(tracked):
    """At a track's first detection the covariance is the one-scan start's (position r0^2, velocity 300^2); while
    its second is missed it keeps it; after the second, the differenced velocity's (2 r^2 / elapsed^2)."""
    cov = tracked[keys.STATE_COV]
    r2 = 4.0**2  # the prior of the measurement-noise estimate, r0 = 4 m
    first = torch.diag(cov[0, 4])
    torch.testing.assert_close(first[[0, 3, 6]], torch.full((3,), r2))
    torch.testing.assert_close(first[[1, 4, 7]], torch.full((3,), 300.0**2))
    torch.testing.assert_close(cov[1, 1], cov[1, 0])  # the second detection missed: the one-scan start's still
    second = torch.diag(cov[0, 5])
    torch.testing.assert_close(second[[1, 4, 7]], torch.full((3,), 2 * r2))
    torch.testing.assert_close(cov[0, 5, 0, 1], torch.tensor(r2))


def test_tracker_step_and_track_give_the_same_covariance(tracker, z, tracked):
    tracker.reset(z.shape[0])
    stepped = torch.stack([tracker.step(z[:, t]).get(keys.FUSED_COV) for t in range(z.shape[1])], 1)
    cov = tracked[keys.STATE_COV]
    assert torch.isnan(cov[0, :4]).all() and torch.isnan(stepped[0, :4]).all()  # no estimate yet
    assert torch.isfinite(cov[0, 4:]).all() and torch.isfinite(cov[1:]).all()
    torch.testing.assert_close(stepped, cov, rtol=1e-5, atol=1e-5, equal_nan=True)
    assert keys.STATE_COV not in tracker.track(z[:, :3]).keys()  # asked for only


def test_experts_alone_give_each_experts_own_covariance(tracker, z):
    net, M = tracker.net, tracker.net.n_experts
    with torch.no_grad():
        out, carry = net.rollout(z[:, :10].unsqueeze(1).expand(-1, M, -1, -1), experts_alone=True, return_cov=True)
    assert out[keys.STATE_COV].shape == (z.shape[0], 10, M, 9, 9)
    assert torch.equal(out[keys.STATE_COV][:, -1], carry.get(keys.EXPERT_AUG_COV)[..., :9, :9])


def test_the_papers_kalmannet_experts_have_no_covariance_and_say_why(z):
    net = IMMNet()  # the paper's configuration: KalmanNet gives each expert's gain, nothing else
    assert not net.has_cov and keys.FUSED_COV not in [k for k in net.fuse.out_keys]
    with pytest.raises(ValueError, match="carry no covariance: its gain KalmanNetGain"):
        net.rollout(z[:, :5], return_cov=True)
    tracker = Tracker(net)
    with pytest.raises(ValueError, match="carry no covariance"):
        tracker.track(z[:, :5], return_cov=True)
    tracker.reset(z.shape[0])
    assert keys.FUSED_COV not in tracker.step(z[:, 0]).keys(True)


def test_the_analytic_gain_fuses_its_experts_covariance(z):
    net = IMMNet(model_set="configs/model_sets/imm3.yaml", gain={"class_path": "immnet.stages.AnalyticGain"},
                 classifier={"class_path": "immnet.stages.BayesianModeUpdate"})
    assert net.has_cov and net.fuse.cov == keys.EXPERT_COV
    with torch.no_grad():
        out, carry = net.rollout(z[:, :12], return_cov=True)
    assert torch.equal(out[keys.STATE_COV][:, -1], carry.get(keys.FUSED_COV))


def _with_consistency(net: IMMNet, weight) -> IMMNet:
    """``net``'s weights in a network with ``cov_consistency=weight``, float64."""
    other = IMMNet(**(dict(net.config) | {"cov_consistency": weight}))
    other.load_state_dict(net.state_dict())
    return other.double().eval()


def test_the_reported_covariance_is_scaled_by_a_running_mean_of_the_nis(tracker):
    """Float64, every scan: the scale is ``(1 - a) lambda + a min(sum_i mu_i nu_i^T S_i^-1 nu_i / 3, 10)`` with
    ``nu_i``, ``S_i = H P_i H^T + r^2 I`` recomputed here with numpy from the step's own prior, covariance and
    ``r^2``; unchanged at a missed detection; the state and the fused covariance are the network's without it."""
    a = 0.05
    net, plain = _with_consistency(tracker.net, a), _with_consistency(tracker.net, None)
    data = generate(5, seed=12, spec=DataSpec(T=25, min_segment=8))
    z = data[keys.MEASUREMENTS].double().clone()
    z[torch.rand(z.shape[:2], generator=torch.Generator().manual_seed(3)) < 0.2] = math.nan
    z[:, :2] = data[keys.MEASUREMENTS][:, :2].double()  # every track starts at scans 0 and 1: a full step after
    carry, bare = net.initial_carry(5, dtype=torch.float64), plain.initial_carry(5, dtype=torch.float64)
    lam = np.ones(5)
    pos = [0, 3, 6]
    with torch.no_grad():
        for t in range(z.shape[1]):
            carry, bare = net.scan(carry, z[:, t]), plain.scan(bare, z[:, t])
            if t >= 2:
                P = carry.get(keys.EXPERT_AUG_PRIOR_COV).numpy()[..., pos, :][..., pos]  # [B, M, 3, 3]
                nu = z[:, t, None, :].numpy() - carry.get(keys.EXPERT_PRIOR).numpy()[..., pos]
                S = P + carry.get(keys.NOISE_VAR).numpy()[:, None, None, None] * np.eye(3)
                nis = np.einsum("bmi,bmi->bm", nu, np.linalg.solve(S, nu[..., None])[..., 0])
                mu = carry.get(keys.EXPERT_PROBS).numpy()
                seen = np.isfinite(z[:, t].numpy()).all(-1)
                lam = np.where(seen, (1 - a) * lam + a * np.minimum(np.nansum(mu * nis, -1) / 3, 10.0), lam)
            np.testing.assert_allclose(carry.get(keys.COV_SCALE).numpy(), lam, rtol=1e-9)
            assert torch.equal(carry.get(keys.FUSED), bare.get(keys.FUSED))
            assert torch.equal(carry.get(keys.FUSED_COV), bare.get(keys.FUSED_COV))
            torch.testing.assert_close(net.reported_cov(carry), torch.from_numpy(lam)[:, None, None] * bare.get(keys.FUSED_COV),
                                       rtol=1e-12, atol=0)
    assert lam.min() != lam.max() and not np.allclose(lam, 1.0)  # the scale moved, differently per track
    out, _ = net.rollout(z, return_cov=True)
    assert out[keys.STATE_COV].shape == (5, 25, 9, 9)
    assert "cov_consistency" not in plain.config and net.config["cov_consistency"] == a  # a checkpoint keeps it


def test_covariance_consistency_needs_filter_experts_and_a_weight(tracker):
    with pytest.raises(ValueError, match="covariance consistency needs experts"):
        IMMNet(cov_consistency=0.05)  # the paper's KalmanNet experts: no covariance, no NIS
    with pytest.raises(ValueError, match=r"weight in \(0, 1\]"):
        _with_consistency(tracker.net, 1.5)
