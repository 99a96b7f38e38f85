"""Filter experts told each detection's measurement covariance (``FilterGain(r="detection")``, the step's input
``"meas_cov"``): with ``R = r^2 I`` the same numbers as told ``r`` (``r="data"``), bit for bit; with anisotropic
covariances the model-based IMM told them (``IMMTracker(r="detection")``, the core's own scan loop) to FilterPy's
criterion; through ``Tracker`` and ``immnet evaluate``'s method as the rollout; and the refusals."""

import pytest
import torch
import yaml

from immnet import keys
from immnet.config import resolve_path
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.filters.trackers import IMMTracker
from immnet.stages import IMMNet
from immnet.stages.filtering import FilterGain
from immnet.tracking.methods import IMMNetMethod
from immnet.tracking.networks import frame_origin, to_local, to_world
from immnet.tracking.tracker import Tracker

ADAPTIVE = "configs/model_sets/imm4-adaptive.yaml"


def _data(seed: int = 8, T: int = 60):
    data = generate(10, seed=seed, spec=DataSpec(T=T, min_segment=min(20, T // 3)))
    z = data[keys.MEASUREMENTS].double()
    z[3, 20:25] = float("nan")  # missed detections inside a track
    z[5, 1] = float("nan")  # right after the start
    z[7, :3] = float("nan")  # a track first detected at scan 3
    data[keys.MEASUREMENTS] = z
    return data


def _anisotropic(z: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """Random symmetric positive-definite covariances [B, T, 3, 3] (variances 5 to a few hundred m^2, correlated), NaN
    where a scan is missed."""
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(*z.shape[:2], 3, 3, generator=g, dtype=torch.float64)
    R = A @ A.transpose(-1, -2) * 30.0 + 5.0 * torch.eye(3, dtype=torch.float64)
    R[torch.isnan(z).any(-1)] = float("nan")
    return R


def _after_first_detection(z: torch.Tensor) -> torch.Tensor:
    """``[B, T]`` True from each track's first detection on."""
    return ((~torch.isnan(z[..., :1])).cumsum(1) > 0)[..., 0]


def _assert_close_to_its_scale(got: torch.Tensor, want: torch.Tensor, seen: torch.Tensor) -> None:
    """``got`` equals ``want`` to 1e-9 of each track's largest state component, where ``seen``."""
    scale = want.nan_to_num().abs().amax((1, 2), keepdim=True).expand_as(want)
    assert ((got - want).abs() <= 1e-9 * scale)[seen].all()


def _real_imm(r):
    args = yaml.safe_load(resolve_path("configs/methods/real-imm-5s.yaml").read_text())["init_args"]
    return IMMTracker(**{**args, "r": r, "name": f"real-imm-5s-{r}"})


@pytest.mark.parametrize("gain", ["immnet.stages.filtering.FilterGain", "immnet.stages.filtering.KalmanNetFilterGain"])
@pytest.mark.parametrize("start", [1, 2])
def test_told_isotropic_covariance_is_told_r_exactly(gain, start):
    """``R_t = r^2 I`` at every detection: the experts told each detection's covariance give what the experts told each
    track's ``r`` give, exactly (the start's covariance, ``S``, the Joseph update, the likelihoods), for the
    model-based filters and for KalmanNet's (the same untrained weights), a start from one detection or two."""
    data = _data()
    z = data[keys.MEASUREMENTS]
    r = data[keys.R].double()
    R = (r * r)[:, None, None, None] * torch.eye(3, dtype=torch.float64).expand(*z.shape[:2], 3, 3)
    R = torch.where(torch.isnan(z).any(-1)[..., None, None], float("nan"), R)
    nets = []
    for told in ("data", "detection"):
        torch.manual_seed(0)
        g = {"class_path": gain, "init_args": {"r": told, "interaction": "imm"}}
        nets.append(IMMNet(model_set=ADAPTIVE, gain=g, classifier={"class_path": "immnet.stages.BayesianModeUpdate",
                                                                   "init_args": {"from_experts": True}},
                           start_detections=start).double().eval())
    nets[1].load_state_dict(nets[0].state_dict())
    data[keys.MEAS_COV] = R
    with torch.no_grad():
        a, _ = nets[0].rollout(z, r=r, return_cov=True, return_loglik=True)
        b, _ = nets[1].rollout(z, meas_cov=nets[1].told_cov(data), return_cov=True, return_loglik=True)
    for key in (keys.STATE, keys.STATE_COV, keys.ROLLOUT_EXPERT_PROBS, keys.LOGLIK):
        torch.testing.assert_close(b[key], a[key], rtol=0, atol=0, equal_nan=True)
    assert torch.isfinite(a[keys.STATE][:, 5:]).all()


def test_told_anisotropic_covariance_is_the_imm_told_it():
    """Each detection's own correlated covariance: ``IMMTracker(r="detection").network()`` (filter experts told it)
    filters what the IMM told it filters (``track``: the core's scan loop with ``R_t``, its start at the first
    detection with that detection's ``R``) to FilterPy's criterion, 1e-9 of the state's scale; ``R = r^2 I`` would not
    (the test can fail). As ``immnet evaluate``'s method (``Tracker.track`` in each track's frame, float32) it is the
    float32 rollout there exactly, and it reads the data's ``meas_cov``."""
    data = _data()
    z = data[keys.MEASUREMENTS]
    data[keys.MEAS_COV] = _anisotropic(z)
    tracker = _real_imm("detection")
    net = tracker.network()
    assert net.start.told_cov and not net.start.told_r
    with torch.no_grad():
        out, _ = net.rollout(z, meas_cov=net.told_cov(data))
    ours = tracker.track(data)[keys.STATE]
    seen = _after_first_detection(z)
    _assert_close_to_its_scale(out[keys.STATE], ours, seen)
    told_r = _real_imm("data").track(data)[keys.STATE]  # each track's r instead: another filter
    assert ((told_r - ours).abs() > 1e-3)[seen].any()

    method = IMMNetMethod.from_tracker(Tracker(net.float()))
    assert method.needs == (keys.MEAS_COV,)
    got = method.track(data)[keys.STATE]
    origin = frame_origin(net, z)
    with torch.no_grad():
        ref, _ = net.rollout(to_local(z, origin), meas_cov=net.told_cov(data).float())
    torch.testing.assert_close(got[seen], to_world(ref[keys.STATE], origin)[seen], rtol=0, atol=0)
    assert torch.isnan(got[~seen]).all()


def test_streaming_steps_with_each_detections_covariance_are_the_sequence():
    """``Tracker.step(z, R=...)`` scan by scan, for a network told each detection's covariance, is ``Tracker.track`` of
    the sequence with its ``meas_cov``: R is used, not warned about and dropped."""
    data = _data(T=25)
    z = data[keys.MEASUREMENTS]
    R = _anisotropic(z, seed=1)
    data[keys.MEAS_COV] = R
    net = _real_imm("detection").network().float()
    whole = Tracker(net).track(z, meas_cov=net.told_cov(data))[keys.STATE]
    stream = Tracker(net)
    steps = torch.stack([stream.step(z[:, t], R=R[:, t])[keys.FUSED] for t in range(z.shape[1])], 1)
    torch.testing.assert_close(steps, whole, rtol=0, atol=1e-6, equal_nan=True)
    with pytest.raises(ValueError, match=r"give Tracker.step its R \[n_tracks, 3, 3\]"):
        Tracker(net).step(z[:, 0])


def test_refusals_of_a_network_told_each_detections_covariance():
    """One line naming what is missing or wrong: an unknown ``r``; a rollout without ``meas_cov``; data without
    ``meas_cov``; a covariance that is not one at a detection."""
    with pytest.raises(ValueError, match=r"'detection' \(each detection's covariance, 'meas_cov'\) or None "
                                         r"\(estimated per track\), got 'detections'"):
        FilterGain(IMMNet(model_set=ADAPTIVE).model_set, r="detections")
    data = _data(T=10)
    z = data[keys.MEASUREMENTS]
    net = _real_imm("detection").network()
    with pytest.raises(ValueError, match=r"r='detection'\): give the step its input 'meas_cov' \[B, 3, 3\]"):
        net.rollout(z)
    with pytest.raises(ValueError, match="the data holds no 'meas_cov'"):
        net.told_cov(data)
    R = _anisotropic(z)
    R[2, 4] = -R[2, 4]
    data[keys.MEAS_COV] = R
    with pytest.raises(ValueError, match="'meas_cov' of track 2, scan 4 is not a finite symmetric positive-definite"):
        net.told_cov(data)
    other = _real_imm("data").network()
    with pytest.raises(ValueError, match="give it no meas_cov"):
        Tracker(other).track(z, r=data[keys.R], meas_cov=R)


def _corrected(whiten: bool, r: str, seed: int = 0):
    """The IMM told ``r`` (``real-imm-5s``'s filters) with an output correction, its ``out`` layer a constant
    correction ``delta = (1, 2, -1)`` (weights 0, bias set)."""
    config = dict(_real_imm(r).network().config)
    config["dt"] = 1.0
    config["correction"] = {"class_path": "immnet.stages.correct.OutputCorrection",
                            "init_args": {"hidden": 8, "layers": 1, "whiten": whiten}}
    torch.manual_seed(seed)
    net = IMMNet(**config).double().eval()
    with torch.no_grad():
        net.correct.out.bias.copy_(torch.tensor([1.0, 2.0, -1.0]))
    return net


def test_whitened_correction_moves_the_estimate_by_the_noise_factor():
    """``OutputCorrection(whiten=True)`` on filters told each detection's covariance: a constant correction ``delta``
    moves the reported position by ``L delta`` (``R = L L^T`` of the last detection), checked against numpy's Cholesky
    factor: ``|L^-1 shift|^2 = shift^T R^-1 shift = |delta|^2`` and the first column ``R[:, 0] / sqrt(R_00)``; without
    whitening, ``sqrt(tr R / 3) delta``. The filter under it is the filter without a correction, exactly."""
    import numpy as np

    data = _data(T=12)
    z = data[keys.MEASUREMENTS]
    R = _anisotropic(z, seed=2)
    data[keys.MEAS_COV] = R
    delta = torch.tensor([1.0, 2.0, -1.0], dtype=torch.float64)
    bare = _real_imm("detection").network()
    with torch.no_grad():
        base, _ = bare.rollout(z, meas_cov=bare.told_cov(data), return_cov=True)
    for whiten in (True, False):
        net = _corrected(whiten, "detection")
        with torch.no_grad():
            out, _ = net.rollout(z, meas_cov=net.told_cov(data), return_cov=True)
        torch.testing.assert_close(out[keys.STATE_COV], base[keys.STATE_COV], rtol=0, atol=0, equal_nan=True)
        shift = (out[keys.STATE] - base[keys.STATE])[..., 0::3]
        b, t = 0, 6  # a scan with a detection, the correction running
        assert not torch.isnan(z[b, t]).any()
        Rbt = R[b, t].numpy()
        if whiten:
            L = np.linalg.cholesky(Rbt)
            np.testing.assert_allclose(shift[b, t].numpy(), L @ delta.numpy(), rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(shift[b, t].numpy() @ np.linalg.solve(Rbt, shift[b, t].numpy()), 6.0, rtol=1e-9)
            probe = _corrected(True, "detection")
            with torch.no_grad():
                probe.correct.out.bias.copy_(torch.tensor([1.0, 0.0, 0.0]))
                one, _ = probe.rollout(z, meas_cov=probe.told_cov(data))
            np.testing.assert_allclose((one[keys.STATE] - base[keys.STATE])[b, t, 0::3].numpy(),
                                       Rbt[:, 0] / np.sqrt(Rbt[0, 0]), rtol=1e-9)
        else:
            np.testing.assert_allclose(shift[b, t].numpy(), np.sqrt(np.trace(Rbt) / 3) * delta.numpy(), rtol=1e-9)


def test_whitened_features_are_the_innovation_in_the_noise_frame():
    """The whitened features: ``|L^-1 (z - p)|^2 = (z - p)^T R^-1 (z - p)`` and ``sum diag(L^-1 P L^-T) = tr(R^-1 P)``
    (numpy), ``log sqrt(diag R) / 5``; with ``R = r^2 I`` the plain features' columns (the innovation over ``r``, the
    position std over ``r``) and the correction ``r delta``."""
    import numpy as np

    from immnet.stages.correct import cholesky_noise, correction_features, whitened_features

    g = torch.Generator().manual_seed(3)
    B = 5
    A = torch.randn(B, 3, 3, generator=g, dtype=torch.float64)
    R = A @ A.transpose(-1, -2) * 50 + 10 * torch.eye(3, dtype=torch.float64)
    C = torch.randn(B, 9, 9, generator=g, dtype=torch.float64)
    P = C @ C.transpose(-1, -2) * 20
    x = torch.randn(B, 9, generator=g, dtype=torch.float64) * 100
    z = x[:, 0::3] + torch.randn(B, 3, generator=g, dtype=torch.float64) * 30
    mu = torch.softmax(torch.randn(B, 4, generator=g, dtype=torch.float64), -1)
    f = whitened_features(z, x, P, mu, cholesky_noise(R), 5.0)
    for b in range(B):
        d, Rb, Pp = (z[b] - x[b, 0::3]).numpy(), R[b].numpy(), P[b][0::3, 0::3].numpy()
        np.testing.assert_allclose((f[b, :3] ** 2).sum().item(), d @ np.linalg.solve(Rb, d), rtol=1e-9)
        np.testing.assert_allclose((f[b, 10:13] ** 2).sum().item(), np.trace(np.linalg.solve(Rb, Pp)), rtol=1e-9)
        np.testing.assert_allclose(f[b, 23:26].numpy(), np.log(np.sqrt(np.diag(Rb)) / 5.0), rtol=1e-12)
    r = torch.tensor([[7.0], [20.0], [3.0], [50.0], [11.0]], dtype=torch.float64)
    iso = (r * r)[..., None] * torch.eye(3, dtype=torch.float64)
    white = whitened_features(z, x, P, mu, cholesky_noise(iso), 5.0)
    plain = correction_features(z, x, P, mu, r, 5.0)
    torch.testing.assert_close(white[:, :23], plain[:, :23], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(white[:, -1], plain[:, -1], rtol=0, atol=0)
    with pytest.raises(ValueError, match="whiten must be true or false, got 'yes'"):
        from immnet.stages.correct import OutputCorrection

        OutputCorrection(IMMNet(model_set=ADAPTIVE).model_set, whiten="yes")


def _data_with_outliers():
    """``_data()`` with two detections 1.5 and 2 km off (tracks 2 and 4), a run of two 1.8 km off (track 1: Huber's
    update takes the second whole, ``immnet.imm.kalman``) and each detection's anisotropic covariance."""
    data = _data()
    z = data[keys.MEASUREMENTS]
    z[2, 30] += 2000.0
    z[4, 10] -= 1500.0
    z[1, 40:42] += 1800.0
    data[keys.MEASUREMENTS] = z
    data[keys.MEAS_COV] = _anisotropic(z)
    return data


@pytest.mark.parametrize("r", ["detection", "data"])
def test_robust_filter_experts_are_the_robust_imm(r):
    """``FilterGain(robust=k)``: Huber's update (the gain ``w K``, the covariance ``P - w K H P`` by Joseph's form with
    ``R + (1/w - 1) S``, Huber's likelihood in the mode update) is the robust IMM's: ``IMMTracker(robust=k).network()``
    filters what its ``track`` filters (the core's ``kalman.update``) to 1e-9 of the state's scale, on tracks with
    outliers 1.5-2 km off, where the plain IMM is kilometres away from it (the test can fail)."""
    data = _data_with_outliers()
    z = data[keys.MEASUREMENTS]
    args = yaml.safe_load(resolve_path("configs/methods/real-imm-5s.yaml").read_text())["init_args"]
    tracker = IMMTracker(**{**args, "r": r, "robust": 2.0, "name": "robust"})
    net = tracker.network()
    assert net.gain.robust == 2.0
    with torch.no_grad():
        out, _ = net.rollout(z, meas_cov=net.told_cov(data), r=net.told_r(data), return_cov=True)
    ours = tracker.track(data)[keys.STATE]
    seen = _after_first_detection(z)
    _assert_close_to_its_scale(out[keys.STATE], ours, seen)
    plain = IMMTracker(**{**args, "r": r, "name": "plain"}).track(data)[keys.STATE]
    assert ((plain - ours).abs() > 500.0)[seen].any()
    with pytest.raises(ValueError, match="robust must be None \\(off\\) or Huber's k"):
        FilterGain(net.model_set, robust=-1.0)
    with pytest.raises(ValueError, match="re-acquisition reads the whole innovation: it takes modes 'joint'"):
        FilterGain(net.model_set, robust=2.0, reacquire=True, modes="axis")


RADAR = ["radar-imm-5s", "radar-imm-11s", "radar-imm-robust-5s", "radar-imm-robust-11s"]


@pytest.mark.parametrize("name", RADAR)
def test_each_radar_imm_is_immnet_with_nothing_learned(name):
    """Issue 21, item 1, for the IMMs told each plot's covariance (``r: detection``, plain and robust): the registry's
    method equals its ``network()`` (filter experts told ``meas_cov``, Huber's update where the method has one) to
    FilterPy's criterion, with outliers 1.5-2 km off among correlated covariances."""
    from immnet.filters.methods import build_method

    data = _data_with_outliers()
    z = data[keys.MEASUREMENTS]
    method = build_method(name)
    net = method.network()
    assert net.start.told_cov and (net.gain.robust is not None) == ("robust" in name)
    with torch.no_grad():
        out, _ = net.rollout(z, meas_cov=net.told_cov(data))
    ours = method.track(data)[keys.STATE]
    seen = _after_first_detection(z)
    _assert_close_to_its_scale(out[keys.STATE], ours, seen)


def _kalmannet_of(tracker: IMMTracker, **gain) -> IMMNet:
    """``tracker.network()`` with KalmanNet filter experts in place of its ``FilterGain`` (the same model noise, ``r``,
    start and interaction; ``gain`` more of ``KalmanNetFilterGain``'s arguments), its learned outputs zero: the noise
    multipliers ``exp(0) = 1`` and no gain correction, so that it is the model-based filter until its weights move."""
    net = tracker.network()
    args = {"model_noise": tracker.sigma_q, "r": tracker.r, "interaction": "imm", "onset": False,
            "start_acc_std": net.gain.start_acc_var[0, 0].sqrt().item(), **gain}
    kn = IMMNet(model_set=net.model_set, dt=net.dt, p_stay=tracker._p_stay, start_detections=1,
                gain={"class_path": "immnet.stages.filtering.KalmanNetFilterGain", "init_args": args},
                classifier={"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"from_experts": True}})
    kn = kn.to(torch.float64).eval()
    with torch.no_grad():
        kn.gain.fc2b.weight.zero_()
        kn.gain.fc2b.bias.zero_()
    return kn


@pytest.mark.parametrize("reacquire", [None, True])
def test_robust_kalmannet_experts_are_the_robust_imm_until_they_learn(reacquire):
    """``KalmanNetFilterGain(robust=k, reacquire=...)``: the KalmanNet filter experts take Huber's update and
    re-acquisition as ``FilterGain`` does. With their learned outputs at zero they filter what the robust IMM filters
    (``IMMTracker(robust=k, reacquire=...).track``, the core's loop) to 1e-9 of the state's scale, on tracks with
    outliers 1.5-2 km off, where the same experts without the robust update are kilometres away (the test can fail)."""
    data = _data_with_outliers()
    z = data[keys.MEASUREMENTS]
    args = yaml.safe_load(resolve_path("configs/methods/real-imm-5s.yaml").read_text())["init_args"]
    tracker = IMMTracker(**{**args, "r": "detection", "robust": 2.0, "reacquire": reacquire, "name": "robust"})
    kn = _kalmannet_of(tracker, robust=2.0, reacquire=reacquire)
    assert kn.gain.robust == 2.0 and (kn.gain.reacquire is None) == (reacquire is None)
    with torch.no_grad():
        out, _ = kn.rollout(z, meas_cov=kn.told_cov(data))
        plain, _ = _kalmannet_of(tracker).rollout(z, meas_cov=kn.told_cov(data))
    ours = tracker.track(data)[keys.STATE]
    seen = _after_first_detection(z)
    _assert_close_to_its_scale(out[keys.STATE], ours, seen)
    assert ((plain[keys.STATE] - ours).abs() > 500.0)[seen].any()


def test_robust_weight_bounds_the_learned_gain_correction_too():
    """Huber's weight ``w`` scales the KalmanNet experts' whole gain, ``w (K + delta)``, its learned correction
    ``delta`` with the Kalman gain: from one carry, a network whose correction is not zero gives on a plot 2 km off
    ``w`` times the gain the same network gives without the robust update, with weights below 1 (a correction added
    after the weight, ``w K + delta``, fails it)."""
    data = _data_with_outliers()
    z = data[keys.MEASUREMENTS][2:3]  # track 2: one detection 2 km off at scan 30
    cov = data[keys.MEAS_COV][2:3]
    args = yaml.safe_load(resolve_path("configs/methods/real-imm-5s.yaml").read_text())["init_args"]
    tracker = IMMTracker(**{**args, "r": "detection", "name": "robust"})
    robust, plain = (_kalmannet_of(tracker, robust=k) for k in (2.0, None))
    with torch.no_grad():
        for net in (robust, plain):
            net.gain.fc2b.bias[:, :27].fill_(0.5)  # a learned correction of every gain entry (bounded: gain_scale)
        carry = plain.initial_carry(1, dtype=torch.float64)
        for t in range(30):  # the track up to the far plot, by the network without the robust update
            carry = plain.scan(carry, z[:, t], meas_cov=cov[:, t]).select(*plain.carry_keys)
        spare = {keys.ROBUST_SPARE: torch.zeros(1, dtype=torch.float64)}  # no far plot before this one
        outs = [net.scan(carry.clone().update(spare) if net is robust else carry, z[:, 30], meas_cov=cov[:, 30])
                for net in (robust, plain)]
    w = outs[0].get(keys.EXPERT_ROBUST_WEIGHT)
    assert (w < 0.5).all()
    delta = outs[1].get(keys.EXPERT_GAIN)
    torch.testing.assert_close(outs[0].get(keys.EXPERT_GAIN), w[..., None, None] * delta, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("r", [30.0, "data"])
def test_robust_update_per_axis_is_the_per_axis_imms(r):
    """Modes per group take Huber's update too: each group's weight from its own innovation (``FilterGain(robust=k,
    modes="axis")``, the gain of ``R' = R + D S D``). ``PerAxisIMMTracker(robust=k).network()`` filters what its
    ``track`` filters (three one-coordinate IMMs through the core's loop, each its own Huber weight and isolated-plot
    rule) to 1e-9 of the state's scale, on tracks with outliers 1.5-2 km off along one axis or all three, where the
    plain per-axis IMM is kilometres away (the test can fail)."""
    from immnet.filters.per_axis import PerAxisIMMTracker

    data = _data_with_outliers()
    z = data[keys.MEASUREMENTS]
    z[6, 25, 2] += 1800.0  # one axis alone far: only its weight drops
    data[keys.MEASUREMENTS] = z
    data[keys.R] = torch.full((z.shape[0],), 30.0, dtype=torch.float64) + torch.arange(z.shape[0])
    args = yaml.safe_load(resolve_path("configs/methods/real-imm-singer.yaml").read_text())["init_args"]
    tracker = PerAxisIMMTracker(**{**args, "r": r, "robust": 2.0, "name": "robust"})
    net = tracker.network()
    assert net.gain.robust == 2.0
    with torch.no_grad():
        out, _ = net.rollout(z, r=net.told_r(data))
    ours = tracker.track(data)[keys.STATE]
    seen = _after_first_detection(z)
    _assert_close_to_its_scale(out[keys.STATE], ours, seen)
    plain = PerAxisIMMTracker(**{**args, "r": r, "name": "plain"}).track(data)[keys.STATE]
    assert ((plain - ours).abs() > 500.0)[seen].any()


@pytest.mark.parametrize("modes", ["joint", "axis"])
def test_a_robust_update_passes_finite_gradients_to_a_learned_gain(modes):
    """Training a KalmanNet gain with Huber's update: the loss's gradient through the weight is finite at missed
    scans and plots within ``k`` (``sqrt(0)``'s infinite derivative once made every batch's gradient NaN, every
    training step skipped), and nonzero."""
    data = _data_with_outliers()
    z = data[keys.MEASUREMENTS][:6, :40]
    tracker = _real_imm(30.0) if modes == "joint" else None
    if tracker is None:
        from immnet.filters.per_axis import PerAxisIMMTracker

        args = yaml.safe_load(resolve_path("configs/methods/real-imm-singer.yaml").read_text())["init_args"]
        tracker = PerAxisIMMTracker(**{**args, "r": 30.0, "name": "axis"})
        net = tracker.network()
        kn = IMMNet(model_set=net.model_set, dt=net.dt, p_stay=tracker._p_stay, start_detections=1, modes="axis",
                    gain={"class_path": "immnet.stages.filtering.KalmanNetFilterGain", "init_args": {
                        "model_noise": tracker.sigma_q, "r": 30.0, "interaction": "imm", "onset": False, "robust": 2.0}},
                    classifier={"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"from_experts": True}})
        kn = kn.double()
    else:
        kn = _kalmannet_of(tracker, robust=2.0).train()
    out, _ = kn.rollout(z)
    loss = out[keys.STATE].nan_to_num().square().mean()
    loss.backward()
    grads = [p.grad for p in kn.gain.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)


def test_whitened_classifier_reads_positions_in_the_noise_stds_of_the_heading_frame():
    """``TransformerClassifier(whiten=True)``: the plot's covariance ``R`` turned into the heading frame (``Rot R
    Rot^T``, along-track, left, up) gives one std per axis, and each position feature is the rotated difference over
    it (``slog(d / std, 1)``) in place of fixed metres; velocities and accelerations as before. Checked against a
    hand computation with numpy in float64 for a track flying north (along-track = north, left = west) and at 30
    degrees, a covariance with an east-north correlation."""
    import math

    import numpy as np

    from immnet.motion import ModelSet
    from immnet.stages.classify import TransformerClassifier, noise_scale

    R = torch.tensor([[[400.0, 100.0, 0.0], [100.0, 2500.0, 0.0], [0.0, 0.0, 900.0]]], dtype=torch.float64)
    for heading in (90.0, 30.0):  # degrees from east, counter-clockwise
        h = math.radians(heading)
        c, s = math.cos(h), math.sin(h)
        rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        want = np.sqrt(np.diag(rot @ R[0].numpy() @ rot.T))
        got = noise_scale(R, torch.tensor([c], dtype=torch.float64), torch.tensor([s], dtype=torch.float64))
        np.testing.assert_allclose(got[0].numpy(), want, rtol=1e-12)
    cls = TransformerClassifier(ModelSet.from_config("configs/model_sets/imm4.yaml"), dt=5.0, window=4, whiten=True)
    g = torch.Generator().manual_seed(0)
    hist = torch.randn(1, 4, 12, generator=g, dtype=torch.float64) * 300.0
    fused = torch.zeros(1, 9, dtype=torch.float64)
    fused[0, [0, 3, 6]] = torch.tensor([1000.0, -2000.0, 9000.0], dtype=torch.float64)
    fused[0, [1, 4, 7]] = torch.tensor([0.0, 200.0, 0.0], dtype=torch.float64)  # north
    tz, tx, (c, s, scale) = cls.tokens(hist, fused, None, R)
    torch.testing.assert_close(scale[0], torch.tensor([50.0, 20.0, 30.0], dtype=torch.float64))
    d = (hist[0, :, :3] - fused[0, [0, 3, 6]]).numpy()
    rotated = np.stack([d[:, 1], -d[:, 0], d[:, 2]], -1) / np.array([50.0, 20.0, 30.0])
    np.testing.assert_allclose(tz[0, :, :3].numpy(), np.sign(rotated) * np.log1p(np.abs(rotated)), rtol=1e-12)
    plain = TransformerClassifier(ModelSet.from_config("configs/model_sets/imm4.yaml"), dt=5.0, window=4)
    tz0, tx0, _ = plain.tokens(hist, fused, None)
    torch.testing.assert_close(tx[..., 3:9], tx0[..., 3:9])  # velocities and accelerations: the same
    assert not torch.allclose(tx[..., :3], tx0[..., :3])


def test_an_untrained_whitened_classifier_is_the_imms_mode_update():
    """A network told each plot's covariance with ``BayesTransformerClassifier(whiten=True)``: the classifier reads
    the carried covariance (wired into the step), and untrained (its correction's last layer zero) it is the IMM's
    Bayesian mode update exactly: the robust told IMM's outputs (``BayesianModeUpdate``), to 1e-12 of the scale."""
    data = _data_with_outliers()
    z = data[keys.MEASUREMENTS]
    tracker = _real_imm("detection")
    net = tracker.network()
    gain = {"class_path": "immnet.stages.filtering.FilterGain", "init_args": {
        "model_noise": tracker.sigma_q, "r": "detection", "interaction": "imm", "onset": False,
        "start_acc_std": net.gain.start_acc_var[0, 0].sqrt().item(), "robust": 2.5}}
    nets = [IMMNet(model_set=net.model_set, dt=net.dt, p_stay=tracker._p_stay, start_detections=1, gain=gain,
                   classifier=classifier).double().eval()
            for classifier in ({"class_path": "immnet.stages.BayesTransformerClassifier", "init_args": {"whiten": True}},
                               {"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"from_experts": True}})]
    assert keys.NOISE_VAR in nets[0].classify.in_keys
    with torch.no_grad():
        outs = [n.rollout(z, meas_cov=n.told_cov(data))[0][keys.STATE] for n in nets]
    _assert_close_to_its_scale(outs[0], outs[1], _after_first_detection(z))


@pytest.mark.parametrize("name", ["real", "general"])
def test_a_robust_shipped_network_streams_as_it_tracks(name):
    """``Tracker.pretrained(name, robust=3.5)`` (``real``: modes per axis, the spare carried per group; ``general``:
    KalmanNet filter experts): ``step`` scan by scan gives ``track``'s estimates on tracks with far plots, and the
    robust update acts (over the scans of far plots the robust track's worst error is below half the plain one's; the
    test can fail)."""
    data = _data_with_outliers()
    z = data[keys.MEASUREMENTS][:, :45].float()
    robust, plain = Tracker.pretrained(name, robust=3.5), Tracker.pretrained(name)
    whole = robust.track(z)[keys.STATE]
    stream = Tracker.pretrained(name, robust=3.5)
    steps = torch.stack([stream.step(z[:, t])[keys.FUSED] for t in range(z.shape[1])], 1)
    torch.testing.assert_close(steps, whole, rtol=0, atol=1e-3, equal_nan=True)
    far = ([2, 4, 1, 1], [30, 10, 40, 41])  # the scans of the far plots (and the one after the run's first)
    truth = data[keys.STATES][far][:, [0, 3, 6]].float()
    error = {n: (out[far][:, [0, 3, 6]] - truth).norm(dim=-1).max() for n, out in (
        ("robust", whole), ("plain", plain.track(z)[keys.STATE]))}
    assert error["robust"] < 0.5 * error["plain"], error


@pytest.mark.parametrize("stage, arg", [("TransformerClassifier", "whiten"), ("TransformerClassifier", "interval_input"),
                                        ("KalmanNetGain", "interval_input")])
def test_a_switch_that_is_not_a_bool_is_refused(stage, arg):
    """A network's switches are true or false: ``"false"`` (a quoted YAML value) is refused by name rather than read
    as true through ``bool``, as the output correction's ``whiten`` already was."""
    import immnet.stages as stages

    model_set = IMMNet(model_set=ADAPTIVE).model_set
    with pytest.raises(ValueError, match=f"{arg} must be true or false, got 'false'"):
        getattr(stages, stage)(model_set, **{arg: "false"})
    assert getattr(getattr(stages, stage)(model_set, **{arg: True}), arg) is True
