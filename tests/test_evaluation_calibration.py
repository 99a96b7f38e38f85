"""Covariance out and its calibration (``immnet.evaluation.calibration``): a Kalman filter told the true
linear-Gaussian model is consistent, so its 95 % ellipsoids hold the truth at 95 % of the scans (NEES is
chi-square with 3 degrees of freedom); a filter told a 4x too small process noise is overconfident. On
3D-LAST the shipped IMMNet's and imm-ekf's fused covariances hold the truth at about the levels they claim."""

import pytest
import torch
from tensordict import TensorDict

from immnet import keys
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.evaluation.calibration import chi2_3_cdf, coverage, position_nees, track_coverage
from immnet.filters.methods import build_method
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


@pytest.fixture(scope="module")
def last():
    """3D-LAST, 48 trajectories of 200 scans, a seed no training, tuning or test set uses."""
    return generate(48, seed=20261202, spec=DataSpec(T=200))


@pytest.fixture(scope="module")
def last_5s():
    """The same at U[4.5, 5.5] s scans, 120 scans."""
    return generate(48, seed=20261202, spec=DataSpec(T=120, dt=5.0, dt_jitter=0.5))


@pytest.mark.parametrize("name", ["immnet", "imm-ekf", "immnet-general"])
def test_on_3dlast_the_95_ellipsoid_holds_the_truth_at_about_95_percent(name, last):
    """Scans 20 on. Measured at 95 % (99 %): on these 48, immnet 0.947 (0.982), imm-ekf 0.937 (0.979); on 300
    trajectories of seed 99, 0.940 and 0.931 (docs/evaluation.md, "Calibration"), a little less in the 20 s
    after a switch of mode (0.92, 0.91), where the mode probabilities have not yet moved."""
    scores = track_coverage(build_method(name, return_cov=True), last, from_scan=20)
    cov = scores["coverage"]
    assert 0.90 <= cov[0.95] <= 0.98 and 0.44 <= cov[0.5] <= 0.58 and 0.96 <= cov[0.99], scores


def test_the_default_networks_covariance_holds_on_3dlast_at_radar_scans(last_5s):
    """The general network (the default; its covariance consistency on, docs/immnet.md) at U[4.5, 5.5] s."""
    scores = track_coverage(build_method("immnet-general", return_cov=True), last_5s, from_scan=20)
    cov = scores["coverage"]
    assert 0.90 <= cov[0.95] <= 0.98 and 0.44 <= cov[0.5] <= 0.58 and 0.96 <= cov[0.99], scores


def test_the_calibration_script_writes_its_json_and_figure(tmp_path):
    """``scripts/calibration.py`` (docs/evaluation.md, "Calibration"): the coverages as JSON, the figure as PNG;
    a method without a covariance is refused by name."""
    import json
    import runpy
    import sys

    from immnet.config import REPO_ROOT

    script = str(REPO_ROOT / "scripts" / "calibration.py")
    argv = ["calibration.py", "--generate", "6", "--T", "120", "--seed", "3", "--methods", "imm-tuned",
            "--json", str(tmp_path / "c.json"), "--figure", str(tmp_path / "c.png")]
    old, sys.argv = sys.argv, argv
    try:
        with pytest.raises(SystemExit) as done:
            runpy.run_path(script, run_name="__main__")
        assert done.value.code == 0
        report = json.loads((tmp_path / "c.json").read_text())
        curve = report["methods"]["imm-tuned"]["coverage"]
        assert report["trajectories"] == 6 and 0 <= curve["0.95"] <= 1 and len(curve) >= 20
        assert (tmp_path / "c.png").read_bytes()[:4] == b"\x89PNG"
        sys.argv = argv[:7] + ["--methods", "measurements"]
        with pytest.raises(SystemExit) as refused:
            runpy.run_path(script, run_name="__main__")
        assert refused.value.code == 2
    finally:
        sys.argv = old


def test_the_calibration_scripts_consistency_rows_are_the_exported_networks(tmp_path):
    """``--consistency CKPT=W``: the row of weight W is the network exported with ``cov_consistency`` W
    (``export_weights(settings=...)``) scored as a method, and differs from the network as it is."""
    import json
    import runpy
    import sys

    from immnet.checkpoints import shipped
    from immnet.config import REPO_ROOT
    from immnet.data.generate import generate
    from immnet.data.spec import DataSpec
    from immnet.evaluation.calibration import track_coverage
    from immnet.training.export import export_weights
    from immnet.tracking.methods import IMMNetMethod

    script = str(REPO_ROOT / "scripts" / "calibration.py")
    ckpt = shipped("real")  # 1 s, as generated here
    argv = ["calibration.py", "--generate", "4", "--T", "120", "--seed", "5", "--methods", "imm-tuned",
            "--consistency", f"{ckpt}=0.5", "--json", str(tmp_path / "c.json")]
    old, sys.argv = sys.argv, argv
    try:
        with pytest.raises(SystemExit) as done:
            runpy.run_path(script, run_name="__main__")
        assert done.value.code == 0
    finally:
        sys.argv = old
    rows = json.loads((tmp_path / "c.json").read_text())["methods"]
    exported = export_weights(ckpt, tmp_path / "w.ckpt", {"cov_consistency": 0.5})
    data = generate(4, seed=5, spec=DataSpec(T=120))
    direct = track_coverage(IMMNetMethod(str(exported), return_cov=True), data, 20)
    row = rows[f"{ckpt.stem}, consistency 0.5"]
    assert row["nees_mean"] == pytest.approx(direct["nees_mean"], abs=1e-4)
    assert row["nees_mean"] != pytest.approx(rows[ckpt.stem]["nees_mean"], abs=1e-3)
