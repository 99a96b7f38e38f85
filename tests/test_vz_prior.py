"""A prior on the vertical speed at a track's start (``IMMTracker(vz_std=...)``, ``FilterGain(start_vz_std=...)``):
the start against the Bayes posterior computed apart (information form, float64 numpy), the model-based IMM's two
runtimes (``track`` and ``network()``) equal with it, re-acquisition's restart included, and the refusals."""

import numpy as np
import pytest
import torch
import yaml

from immnet import keys
from immnet.config import resolve_path
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.filters.imm import ACC_STD, VEL_STD
from immnet.filters.trackers import IMMTracker
from immnet.imm.kalman import start_state
from immnet.stages import IMMNet

VZ = 5.0


def _data(seed: int = 3, T: int = 40):
    data = generate(8, seed=seed, spec=DataSpec(T=T, min_segment=min(20, T // 3)))
    z = data[keys.MEASUREMENTS].double()
    z[2, 10:14] = float("nan")
    z[4, :3] = float("nan")  # a track first detected at scan 3
    data[keys.MEASUREMENTS] = z
    return data


def _imm(**changes) -> IMMTracker:
    args = yaml.safe_load(resolve_path("configs/methods/real-imm-5s.yaml").read_text())["init_args"]
    return IMMTracker(**{**args, **changes})


def _posterior(x: np.ndarray, P: np.ndarray, vz_std: float) -> tuple[np.ndarray, np.ndarray]:
    """``N(x, P)`` times the likelihood of measuring the vertical speed (index 7) as 0 with variance ``vz_std^2``, in
    information form: ``P' = (P^-1 + e7 e7^T / vz^2)^-1``, ``x' = P' P^-1 x``."""
    e = np.zeros(len(x))
    e[7] = 1.0
    info = np.linalg.inv(P) + np.outer(e, e) / vz_std**2
    post = np.linalg.inv(info)
    return post @ (np.linalg.inv(P) @ x), post


def test_the_one_point_start_is_the_bayes_posterior():
    z = torch.tensor([[1000.0, -2000.0, 9000.0], [5.0, 6.0, 7.0]], dtype=torch.float64)
    R = torch.diag_embed(torch.tensor([[900.0, 1600.0, 4.0e4], [100.0, 100.0, 100.0]], dtype=torch.float64))
    x0, P0 = start_state(z, R, VEL_STD, ACC_STD)
    x1, P1 = start_state(z, R, VEL_STD, ACC_STD, VZ)
    for b in range(2):
        want_x, want_P = _posterior(x0[b].numpy(), P0[b].numpy(), VZ)
        np.testing.assert_allclose(x1[b].numpy(), want_x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(P1[b].numpy(), want_P, rtol=1e-9, atol=1e-12)
    assert abs(float(P1[0, 7, 7]) - VZ**2) < 0.01  # one plot says nothing of the speed: the prior's, nearly
    assert torch.equal(P1[:, 4, 4], P0[:, 4, 4])  # the horizontal speeds untouched


def test_the_two_point_start_of_the_filter_experts_is_the_bayes_posterior():
    """A network that starts from two detections (differenced velocity, correlated with the position): after the
    second detection each expert's state and covariance equal the same network's without the prior, updated by the
    prior in information form."""
    data = _data()
    z = data[keys.MEASUREMENTS][:, :2]
    z[4] = data[keys.MEASUREMENTS][0, :2]  # every track detected at both scans
    r = torch.full((z.shape[0],), 100.0, dtype=torch.float64)  # a far radar's plots: the pair's vz uncertain by ~140 m/s
    carries = []
    for vz in (None, VZ):
        g = {"class_path": "immnet.stages.filtering.FilterGain",
             "init_args": {"r": "data", "interaction": "imm", "start_vz_std": vz}}
        net = IMMNet(model_set="configs/model_sets/imm4.yaml", gain=g, start_detections=2,
                     classifier={"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"from_experts": True}})
        with torch.no_grad():
            _, carry = net.double().eval().rollout(z, r=r)
        carries.append(carry)
    x0, P0 = carries[0][keys.EXPERT_POST], carries[0][keys.EXPERT_AUG_COV]
    x1, P1 = carries[1][keys.EXPERT_POST], carries[1][keys.EXPERT_AUG_COV]
    assert float(P0[..., 7, 7].min()) > 10 * VZ**2  # the pair alone: far less sure of the vertical speed
    for b in range(z.shape[0]):
        for m in range(x0.shape[1]):
            P = P0[b, m].numpy()
            x = np.concatenate([x0[b, m].numpy(), np.zeros(P.shape[0] - 9)])
            keep = np.diag(P) > 0  # the turn rate's row is zero for a model without one
            want_x, want_P = _posterior(x[keep], P[np.ix_(keep, keep)], VZ)
            np.testing.assert_allclose(x1[b, m].numpy(), want_x[:9], rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(P1[b, m].numpy()[np.ix_(keep, keep)], want_P, rtol=1e-8, atol=1e-9)


@pytest.mark.parametrize("changes", [{"r": 40.0}, {"r": "detection"},
                                     {"r": "detection", "robust": 2.5, "reacquire": True}])
def test_both_runtimes_of_a_told_imm_with_the_prior_agree(changes):
    """``track`` (the core's scan loop) and ``network()`` (IMMNet's step) with ``vz_std``: the same estimates to 1e-9
    of each track's scale, and not those without the prior (the test can fail)."""
    data = _data()
    z = data[keys.MEASUREMENTS]
    g = torch.Generator().manual_seed(1)
    A = torch.randn(*z.shape[:2], 3, 3, generator=g, dtype=torch.float64)
    R = A @ A.transpose(-1, -2) * 30.0 + 5.0 * torch.eye(3, dtype=torch.float64)
    data[keys.MEAS_COV] = torch.where(torch.isnan(z).any(-1)[..., None, None], float("nan"), R)
    tracker = _imm(vz_std=VZ, name="prior", **changes)
    net = tracker.network()
    assert net.gain.start_vz_std == VZ
    told = {"meas_cov": net.told_cov(data)} if changes["r"] == "detection" else {}
    with torch.no_grad():
        out, _ = net.rollout(z, **told)
    ours = tracker.track(data)[keys.STATE]
    seen = ((~torch.isnan(z[..., :1])).cumsum(1) > 0)[..., 0]
    scale = ours.nan_to_num().abs().amax((1, 2), keepdim=True).expand_as(ours)
    assert ((out[keys.STATE] - ours).abs() <= 1e-9 * scale)[seen].all()
    without = _imm(name="none", **changes).track(data)[keys.STATE]
    assert ((without - ours)[..., 7].abs() > 1e-3)[seen].any()


@pytest.mark.parametrize("vz_std", [0.0, -1.0, float("nan"), float("inf"), True, "5"])
def test_a_vz_std_that_is_no_std_is_refused(vz_std):
    with pytest.raises(ValueError, match="vz_std .* must be a number > 0 or None"):
        _imm(vz_std=vz_std)
    with pytest.raises(ValueError, match="vz_std .* must be a number > 0 or None"):
        IMMNet(model_set="configs/model_sets/imm4.yaml", gain={
            "class_path": "immnet.stages.filtering.FilterGain", "init_args": {"start_vz_std": vz_std}})


def test_modes_per_group_refuse_the_prior():
    with pytest.raises(ValueError, match="no vz_std"):
        _imm(modes="channel", r=40.0, vz_std=VZ)
