"""Re-acquisition (``immnet.imm.reacquire``): a start its next plot contradicts, and a run of agreeing detections far
outside every filter's gate, restart the track; a no-op where neither happens; the same in IMMNet's step."""

import math

import pytest
import torch
import yaml
from tensordict import TensorDict

from immnet import keys
from immnet.config import resolve_path
from immnet.filters.trackers import IMMTracker
from immnet.imm.reacquire import Reacquire
from immnet.stages.filtering import FilterGain
from immnet.tracking.tracker import Tracker

RULE = {"scans": 2, "gate": 25.0, "speed": 300.0, "climb": 50.0, "reject": True}
R_DIAG = (40.0**2, 100.0**2, 170.0**2)  # a plot's noise at ~50 km (m^2): 40 m in range, 0.12 / 0.2 deg across


def _robust(reacquire=None) -> IMMTracker:
    args = yaml.safe_load(resolve_path("configs/methods/radar-imm-robust-5s.yaml").read_text())["init_args"]
    return IMMTracker(**{**args, "reacquire": reacquire})


def _scene(B: int = 4, T: int = 40, dt: float = 5.0, seed: int = 0) -> TensorDict:
    """Straight and level tracks at 216 m/s seen every ``dt`` s with the plot noise ``R_DIAG``."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T, dtype=torch.float64) * dt
    v = torch.tensor([180.0, -120.0, 0.0], dtype=torch.float64)
    truth = (torch.tensor([30e3, 40e3, 9e3], dtype=torch.float64) + t[:, None] * v).expand(B, T, 3).clone()
    R = torch.diag(torch.tensor(R_DIAG, dtype=torch.float64)).expand(B, T, 3, 3).clone()
    z = truth + torch.randn(B, T, 3, generator=g, dtype=torch.float64) * torch.tensor(R_DIAG, dtype=torch.float64).sqrt()
    states = torch.zeros(B, T, 9, dtype=torch.float64)
    states[..., 0::3] = truth
    states[..., 1::3] = v
    return TensorDict({keys.MEASUREMENTS: z, keys.MEAS_COV: R, keys.STATES: states,
                       keys.DT: torch.full((B,), dt, dtype=torch.float64)}, batch_size=[B])


def _error(method, data) -> torch.Tensor:
    est = method.track(data)[keys.STATE][..., 0::3]
    return torch.linalg.vector_norm(est - data[keys.STATES][..., 0::3], dim=-1)  # [B, T]


def test_a_first_plot_3_km_off_restarts_at_the_next():
    """The first plot 3 km north of the truth: the second is 3.7 km from it, beyond 300 m/s over 5 s and three
    standard deviations of the two plots' noise (1.5 km + 0.85 km), so the track restarts there: its estimate at scan 1
    is that plot exactly (a start's), and from scan 2 on it is within 600 m of the truth; Huber's update alone (which
    takes the second far plot of a run whole) leaves a track more than 2 km off at scan 2."""
    data = _scene()
    data[keys.MEASUREMENTS][:, 0, 1] += 3000.0
    z = data[keys.MEASUREMENTS]
    est = _robust(RULE).track(data)[keys.STATE]
    assert torch.equal(est[:, 1, 0::3], z[:, 1])
    assert (est[:, 1, 1::3] == 0).all()  # velocity unknown again, as at a first detection
    after = _error(_robust(RULE), data)
    assert after[:, 2:].max() < 600.0
    before = _error(_robust(), data)
    assert before[:, 2].max() > 2000.0


def test_a_run_of_far_agreeing_plots_restarts_the_track_at_the_second():
    """From scan 20 on the plots lie 3 km east of where the track was (the track is off, as after a start on an
    outlier): scan 20 is far (d^2 far beyond 25 for every filter), scan 21 far again and 1 km from scan 20's, within
    300 m/s of it: the track restarts at scan 21, its estimate that plot; Huber's update alone is still 1 km off there."""
    data = _scene()
    data[keys.MEASUREMENTS][:, 20:, 0] += 3000.0
    data[keys.STATES][:, 20:, 0] += 3000.0  # the truth moved with them: the track is what is off
    z = data[keys.MEASUREMENTS]
    est = _robust(RULE).track(data)[keys.STATE]
    assert torch.equal(est[:, 21, 0::3], z[:, 21])
    assert not torch.equal(est[:, 20, 0::3], z[:, 20])  # one far plot is not a run
    assert _error(_robust(RULE), data)[:, 23:].max() < 600.0
    assert (_error(_robust(), data)[:, 21] > 1000.0).all()


def test_a_far_plot_that_restarts_nothing_is_gated_out():
    """One plot 2.1 km off at scan 12 (d^2 far beyond 25), the next ones true: with ``reject`` the filters take it as
    a missed detection, so every estimate is, bit for bit, the one of the same plots with scan 12 missed (in the IMM
    and in its network); without ``reject`` Huber's update moves the track towards it."""
    data = _scene()
    data[keys.MEASUREMENTS][:, 12, :2] += 1500.0
    missed = data.clone()
    missed[keys.MEASUREMENTS][:, 12] = float("nan")
    method = _robust(RULE)
    gated = method.track(data)[keys.STATE]
    assert torch.equal(gated, method.track(missed)[keys.STATE])
    net = method.network(5.0)
    with torch.no_grad():
        a = net.rollout(data[keys.MEASUREMENTS], meas_cov=net.told_cov(data))[0][keys.STATE]
        b = net.rollout(missed[keys.MEASUREMENTS], meas_cov=net.told_cov(missed))[0][keys.STATE]
    assert torch.equal(a, b)
    huber = _robust({**RULE, "reject": False}).track(data)[keys.STATE]
    assert ((huber[:, 12, 0::3] - gated[:, 12, 0::3]).norm(dim=-1) > 50.0).all()


def test_reach_against_a_hand_computation():
    """``reachable``: one filter predicting the origin with no uncertainty, a plot covariance of 100 m^2 per axis, 2 s:
    horizontally ``60 * 2^2 / 2 + 3 sqrt(200) = 162.43`` m, vertically ``2 * 2^2 / 2 + 3 * 10 = 34`` m."""
    from immnet.imm.reacquire import innovations, reachable

    rule = Reacquire(**RULE)
    x, P = torch.zeros(4, 1, 9, dtype=torch.float64), torch.zeros(4, 1, 9, 9, dtype=torch.float64)
    R = 100.0 * torch.eye(3, dtype=torch.float64).expand(4, 3, 3)
    z = torch.tensor([[162.0, 0.0, 0.0], [163.0, 0.0, 0.0], [0.0, 0.0, 33.9], [0.0, 0.0, 34.1]], dtype=torch.float64)
    nu, S = innovations(z, x, P, R)
    assert reachable(rule, nu, S, 2.0).tolist() == [True, False, True, False]
    assert not reachable(Reacquire(**RULE, accel=None, vertical_accel=None), nu, S, 2.0).any()


def test_a_far_plot_within_the_targets_reach_is_taken_one_beyond_it_gated_out():
    """A plot 700 m east of a straight track at scan 20 (far: d^2 beyond 25 for every filter) lies within an aircraft's
    reach over 5 s (60 m/s^2: 750 m, plus three standard deviations): the update takes it (Huber's weight), where
    without accelerations it is gated out (the estimates those of the same plots with scan 20 missed, bit for bit);
    2.5 km up (2 m/s^2 vertically: 25 m plus three standard deviations) it is gated out either way. The network of
    the filter (IMMNet's step) does the same to 1e-9 of the state's scale."""
    no_reach = {**RULE, "accel": None, "vertical_accel": None}
    for shift, taken in (((700.0, 0.0, 0.0), True), ((0.0, 0.0, 2500.0), False)):
        data = _scene()
        data[keys.MEASUREMENTS][:, 20] += torch.tensor(shift, dtype=torch.float64)
        missed = data.clone()
        missed[keys.MEASUREMENTS][:, 20] = float("nan")
        as_missed = _robust(RULE).track(missed)[keys.STATE]
        assert torch.equal(_robust(no_reach).track(data)[keys.STATE], as_missed)
        method = _robust(RULE)
        ours = method.track(data)[keys.STATE]
        moved = (ours[:, 20, 0::3] - as_missed[:, 20, 0::3]).norm(dim=-1)
        assert (moved > 50.0).all() if taken else torch.equal(ours, as_missed)
        net = method.network(5.0)
        with torch.no_grad():
            out = net.rollout(data[keys.MEASUREMENTS], meas_cov=net.told_cov(data))[0][keys.STATE]
        scale = ours.abs().amax()
        assert ((out - ours).abs() <= 1e-9 * scale).all()


def test_a_no_op_bit_for_bit_on_clean_plots():
    """Clean plots (missed scans, a late first detection included): the filter with re-acquisition is the filter
    without it, bit for bit, and so is the network of each."""
    data = _scene(B=6, T=60, seed=3)
    z = data[keys.MEASUREMENTS]
    z[1, 10:13] = float("nan")
    z[2, :4] = float("nan")
    with_rule, without = _robust(RULE), _robust()
    assert _same(with_rule.track(data)[keys.STATE], without.track(data)[keys.STATE])
    a, b = with_rule.network(5.0), without.network(5.0)
    with torch.no_grad():
        ra = a.rollout(z, meas_cov=a.told_cov(data))[0][keys.STATE]
        rb = b.rollout(z, meas_cov=b.told_cov(data))[0][keys.STATE]
    assert _same(ra, rb)


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Bit for bit, NaN (no estimate before a track's first detection) where the other is NaN."""
    return torch.equal(torch.isnan(a), torch.isnan(b)) and torch.equal(a.nan_to_num(), b.nan_to_num())


def _restarting_scene() -> TensorDict:
    data = _scene(B=5, T=40, seed=1)
    z = data[keys.MEASUREMENTS]
    z[0, 0, 1] += 3000.0  # a start on an outlier
    z[1, 15:, 0] += 3000.0  # a run of far plots
    z[2, 17:19] = float("nan")
    z[2, 19:, 2] -= 2500.0  # a run after missed scans
    z[3, 5] += torch.tensor([1500.0, 1500.0, 0.0], dtype=torch.float64)  # one outlier: no run
    z[4, :3] = float("nan")  # a late first detection, its next plot 4 km off
    z[4, 4, 1] += 4000.0
    return data


def test_the_network_and_the_streaming_tracker_restart_the_same_tracks():
    """``IMMTracker(reacquire=...).network()`` (IMMNet's step, ``FilterGain(reacquire=...)``), ``Tracker.track`` and
    the streaming ``Tracker.step`` restart the tracks the model-based loop restarts, at the same scans: the network's
    rollout agrees to 1e-9 of the estimates' scale, the Tracker's (float32 inside) to 1e-6, and restarts did happen (a
    restarted track's estimate is its plot)."""
    data = _restarting_scene()
    z = data[keys.MEASUREMENTS]
    method = _robust(RULE)
    ours = method.track(data)[keys.STATE]
    assert torch.equal(ours[0, 1, 0::3], z[0, 1]) and torch.equal(ours[1, 16, 0::3], z[1, 16])
    assert torch.equal(ours[2, 20, 0::3], z[2, 20]) and torch.equal(ours[4, 4, 0::3], z[4, 4])
    net = method.network(5.0)
    assert net.gain.reacquire == Reacquire(**RULE)
    with torch.no_grad():
        out, _ = net.rollout(z, meas_cov=net.told_cov(data))
    seen = (~torch.isnan(z[..., :1])).cumsum(1)[..., 0] > 0
    scale = ours.nan_to_num().abs().amax((1, 2), keepdim=True)
    assert ((out[keys.STATE] - ours).abs() <= 1e-9 * scale)[seen].all()
    whole = Tracker(net, max_coast=math.inf).track(z, meas_cov=data[keys.MEAS_COV])[keys.STATE].double()
    assert ((whole - ours).abs() <= 1e-6 * scale)[seen].all()  # float32 inside the Tracker
    stream = Tracker(net, max_coast=math.inf)
    steps = torch.stack([stream.step(z[:, t], R=data[keys.MEAS_COV][:, t])[keys.FUSED] for t in range(z.shape[1])], 1)
    assert ((steps.double() - ours).abs() <= 1e-6 * scale)[seen].all()


@pytest.mark.parametrize("config, message", [
    ({"scans": 1}, "reacquire's scans must be an integer >= 2 (consecutive far detections), got 1"),
    ({"gate": 0.0}, "reacquire's gate must be a finite number > 0, got 0.0"),
    ({"speed": float("inf")}, "reacquire's speed must be a finite number > 0, got inf"),
    ({"climb": -1.0}, "reacquire's climb must be a finite number > 0, got -1.0"),
    ({"reject": 1}, "reacquire's reject must be true or false, got 1"),
    ({"span": 3}, "unknown Reacquire field(s) ['span']; known: ['accel', 'climb', 'gate', 'reject', 'scans', 'speed', "
                  "'vertical_accel']"),
    ({"accel": None}, "reacquire's accel and vertical_accel are both numbers or both None (every far detection "
                      "rejected), got None and 2.0"),
    ({"vertical_accel": -1.0}, "reacquire's vertical_accel must be a finite number >= 0 (m/s^2) or None, got -1.0"),
    ({"accel": True}, "reacquire's accel must be a finite number >= 0 (m/s^2) or None, got True"),
])
def test_refusals(config, message):
    with pytest.raises(ValueError) as err:
        _robust(config)
    assert str(err.value) == message


def test_refused_where_the_rule_cannot_run():
    args = yaml.safe_load(resolve_path("configs/methods/radar-imm-robust-5s.yaml").read_text())["init_args"]
    polar = {"sigma_range": 40.0, "sigma_azimuth_deg": 0.12, "sigma_elevation_deg": 0.2}
    with pytest.raises(ValueError, match="re-acquisition takes a Cartesian measurement model"):
        IMMTracker(**{**args, "r": polar, "reacquire": RULE, "name": "p"})
    with pytest.raises(ValueError, match="re-acquisition reads the whole innovation: it takes modes 'joint'"):
        FilterGain(_robust().model_set, reacquire=RULE, modes="axis")


def test_a_kalman_filter_restarts_too():
    """``KalmanFilterTracker(robust=2.5, reacquire=...)``: the first plot 3 km north, its start restarts at the second plot (the
    estimate there is that plot), and from scan 2 on the track is within 600 m; with Huber's update alone a track is 2 km off at scan 2."""
    from immnet.filters.trackers import KalmanFilterTracker

    data = _scene()
    data[keys.MEASUREMENTS][:, 0, 1] += 3000.0
    model = {"class_path": "immnet.motion.ConstantVelocity", "init_args": {"noise": "continuous"}}
    kf = KalmanFilterTracker(model, r=120.0, sigma_q=1.0, robust=2.5, reacquire=RULE)
    assert torch.equal(kf.track(data)[keys.STATE][:, 1, 0::3], data[keys.MEASUREMENTS][:, 1])
    assert _error(kf, data)[:, 2:].max() < 600.0
    assert _error(KalmanFilterTracker(model, r=120.0, sigma_q=1.0, robust=2.5), data)[:, 2].max() > 2000.0


def test_the_shipped_radar_networks_take_the_rule_by_name_and_by_load():
    """The registry's ``immnet-radar-5s`` (the default on plots at 4.5-5.5 s) carries the robust IMM's rule;
    ``load_network(..., reacquire=None)`` takes it off, and a checkpoint whose gain has none is refused in one line."""
    from immnet.filters.methods import build_method
    from immnet.tracking.networks import load_network

    assert build_method("immnet-radar-5s").net.gain.reacquire == Reacquire(**RULE)
    assert build_method("radar-imm-robust-5s").reacquire == Reacquire(**RULE)
    assert load_network("immnet/pretrained/immnet-radar-5s.ckpt", reacquire=None).gain.reacquire is None
    kalmannet = load_network("immnet/pretrained/immnet.ckpt", reacquire=True, robust=2.5)  # KalmanNet filter experts
    assert kalmannet.gain.reacquire == Reacquire() and kalmannet.gain.robust == 2.5


def test_a_gain_without_filter_experts_refuses_the_rule_and_the_robust_update_in_one_line(tmp_path):
    """The paper's KalmanNet gain learns its gain without a measurement model: re-acquisition and Huber's update, which
    read each expert's innovation covariance, are refused at load, naming the file and its gain."""
    import lightning as L

    from immnet.tracking.networks import load_network
    from immnet.training import Stage2Module

    module = Stage2Module(net={"model_set": "configs/model_sets/imm4.yaml"})
    trainer = L.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False, max_epochs=0)
    trainer.strategy.connect(module)
    path = tmp_path / "net.ckpt"
    trainer.save_checkpoint(path)
    for option, value, what in (("reacquire", True, "re-acquisition needs filter experts"),
                                ("robust", 2.5, "a robust update needs filter experts"),
                                ("start_vz_std", 5.0, "a start's prior on the vertical speed needs filter experts")):
        with pytest.raises(ValueError) as err:
            load_network(path, **{option: value})
        assert str(err.value) == f"{path}: {what}; this checkpoint's gain is immnet.stages.KalmanNetGain"
