"""IMMNet stages: shapes and keys, the stacked layers against torch's, swaps by configuration,
the analytic gains (the paper architecture's and the recipes' ablation) against our KF,
gradients, missed detections and streaming against batched rollouts."""

import copy
import math

import pytest
import torch
import yaml
from torch import nn

from immnet import keys
from immnet.checkpoints import load_checkpoint
from immnet.config import REPO_ROOT
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.imm import kalman
from immnet.motion import ModelSet
from immnet.stages import IMMNet
from immnet.stages.layers import StackedGRUCell, StackedLinear
from immnet.tracking.tracker import Tracker
from immnet.training import Stage2Module

CV_ONLY = [{"class_path": "immnet.motion.ConstantVelocity"}]
ANALYTIC = {"class_path": "immnet.stages.AnalyticGain", "init_args": {"sigma_q": 0.5, "r": 3.0}}
UNIFORM = {"class_path": "immnet.stages.UniformMix"}
BAYES = {"class_path": "immnet.stages.BayesianModeUpdate"}


@pytest.fixture(scope="module")
def data():
    td = generate(6, seed=3, spec=DataSpec(T=60, min_segment=15))
    return td.apply(lambda v: v.float() if v.is_floating_point() else v)


@pytest.mark.parametrize("model_set,M", [("imm3", 3), ("imm4", 4), ("imm4-adaptive", 4), ("imm6", 6)])
def test_every_stage_writes_its_keys_with_shapes(model_set, M, data):
    net = IMMNet(model_set=f"configs/model_sets/{model_set}.yaml")
    carry, _ = None, None
    out, carry = net.rollout(data[keys.MEASUREMENTS][:, :5])
    B = data.batch_size[0]
    td = carry.copy()
    td.set(keys.MEASUREMENT, data[keys.MEASUREMENTS][:, 5])
    expected = {
        net.predict: {keys.EXPERT_PRIOR: (B, M, 9)},
        net.gain: {keys.EXPERT_GAIN: (B, M, 9, 3), (*keys.EXPERT_HIDDEN, "q"): (B, M, 81)},
        net.update: {keys.EXPERT_POST: (B, M, 9)},
        net.classify: {keys.EXPERT_PROBS: (B, M), keys.MODE_LOGITS: (B, M), keys.HISTORY: (B, 20, 12)},
        net.fuse: {keys.FUSED: (B, 9), keys.PREV_FUSED: (B, 9), keys.PREV_EXPERT_PRIOR: (B, M, 9)},
    }
    for stage, written in expected.items():
        assert set(k if isinstance(k, str) else tuple(k) for k in stage.out_keys) >= {
            k if isinstance(k, str) else tuple(k[:2]) for k in written
        }
        td = stage(td)
        for key, shape in written.items():
            assert tuple(td.get(key).shape) == shape, (stage, key)
    assert torch.allclose(td.get(keys.EXPERT_PROBS).sum(-1), torch.ones(B))
    assert out[keys.STATE].shape == (B, 5, 9) and out[keys.ROLLOUT_EXPERT_PROBS].shape == (B, 5, M)


def test_stage_swap_by_configuration_alone(data):
    net = IMMNet(model_set="configs/model_sets/imm3.yaml", gain=ANALYTIC, classifier=BAYES)
    assert type(net.gain).__name__ == "AnalyticGain" and type(net.classify).__name__ == "BayesianModeUpdate"
    out, _ = net.rollout(data[keys.MEASUREMENTS])
    assert torch.isfinite(out[keys.STATE]).all()
    uniform = IMMNet(classifier=UNIFORM)
    out, _ = uniform.rollout(data[keys.MEASUREMENTS][:, :10])
    assert torch.allclose(out[keys.ROLLOUT_EXPERT_PROBS][:, 3:], torch.full((6, 7, 4), 0.25))


def _assert_cv_rollout_is_our_kalman_filter(net, z, sigma, r, P_start):
    """``net`` (one CV expert) rolled out over ``z`` equals immnet.imm.kalman with white-noise
    ``sigma`` and measurement noise ``r``, from the two-point start (position ``z_1``, velocity
    ``z_1 - z_0``) with covariance ``P_start`` [9, 9], scan by scan."""
    out, _ = net.rollout(z)
    dt, ms = 1.0, ModelSet.from_config(CV_ONLY)
    F, Q = ms.F(dt)[0], ms.Q(sigma, dt)[0]
    x = torch.zeros(z.shape[0], 9, dtype=torch.float64)
    x[:, [0, 3, 6]] = z[:, 1]
    x[:, [1, 4, 7]] = (z[:, 1] - z[:, 0]) / dt
    P = P_start.expand(z.shape[0], 9, 9)
    torch.testing.assert_close(out[keys.STATE][:, 1], x)
    for t in range(2, z.shape[1]):
        x, P = kalman.predict(x, P, F, Q)
        x, P, _ = kalman.update(x, P, z[:, t], None, r * r)
        torch.testing.assert_close(out[keys.STATE][:, t], x, rtol=1e-6, atol=1e-6)


def test_analytic_gain_with_cv_expert_equals_our_kalman_filter(data):
    """IMMNet(CV, analytic gain) from its two-point start equals immnet.imm.kalman step by step."""
    net = IMMNet(model_set=CV_ONLY, gain=ANALYTIC, classifier=UNIFORM).double()
    r = 3.0
    P = torch.diag(torch.tensor([r * r, 2 * r * r, 100.0] * 3, dtype=torch.float64))
    _assert_cv_rollout_is_our_kalman_filter(net, data[keys.MEASUREMENTS].double(), 0.5, r, P)


def test_analytic_gain_ablation_with_cv_expert_equals_our_kalman_filter(data):
    """The analytic-gain ablation of the recipes (``FilterGain``: filter experts with their base noise,
    nothing learned), with one CV expert and its r estimate pinned to r0 (prior weight k0 huge),
    equals immnet.imm.kalman from the same two-point start, scan by scan."""
    cfg = yaml.safe_load((REPO_ROOT / "configs/ablations/analytic-gain.yaml").read_text())
    gain = dict(cfg["stages"][0]["config"][1]["model"]["init_args"]["net"]["init_args"]["gain"])
    assert gain["class_path"] == "immnet.stages.filtering.FilterGain"
    sigma, r = 0.5, 3.0
    gain["init_args"] = {"noise_std": (sigma, sigma, 0.01, 0.002, 1e-5), "r0": r, "k0": 1e15}
    net = IMMNet(model_set=CV_ONLY, gain=gain, classifier=UNIFORM).double()
    P = torch.zeros(9, 9, dtype=torch.float64)
    for p_, v_, a_ in ((0, 1, 2), (3, 4, 5), (6, 7, 8)):
        P[p_, p_], P[v_, v_], P[p_, v_], P[v_, p_] = r * r, 2 * r * r, r * r, r * r
        P[a_, a_] = 1.0  # CV carries no acceleration: its value never reaches the estimate
    _assert_cv_rollout_is_our_kalman_filter(net, data[keys.MEASUREMENTS].double(), sigma, r, P)


@pytest.mark.parametrize("expert_weight", [0.0, 0.3])
def test_gradients_reach_every_parameter_in_stage_2(data, expert_weight):
    module = Stage2Module(net={"model_set": "configs/model_sets/imm4.yaml"}, expert_weight=expert_weight)
    out, _ = module.net.rollout(data[keys.MEASUREMENTS][:, :30])
    loss = module.losses(out, _crop(data, 30))[0]
    loss.backward()
    dead = [n for n, p in module.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all() or p.grad.abs().sum() == 0]
    assert not dead, f"no gradient for {dead}"


def _crop(batch, T):
    return batch.apply(lambda v: v[:, :T] if v.dim() >= 2 else v)


def test_missed_detections_leave_the_state_finite(data):
    net = IMMNet()
    z = data[keys.MEASUREMENTS].clone()
    z[:, 10:14] = math.nan
    z[0, 0] = math.nan  # a track that starts one scan late
    z[1, 30:] = math.nan  # a track that coasts to the end
    out, _ = net.rollout(z)
    assert torch.isfinite(out[keys.STATE][:, 1:]).all()
    # coasting follows the experts' predictions: positions keep moving with the velocity
    assert (out[keys.STATE][1, 40, [0, 3, 6]] != out[keys.STATE][1, 30, [0, 3, 6]]).all()


def test_streaming_step_equals_batched_rollout(data):
    tracker = Tracker(IMMNet())
    z = data[keys.MEASUREMENTS][:, :40]
    batched = tracker.track(z)
    tracker.reset(z.shape[0])
    for t in range(z.shape[1]):
        step = tracker.step(z[:, t])
        torch.testing.assert_close(step.get(keys.FUSED), batched[keys.STATE][:, t], rtol=1e-5, atol=1e-4)
        torch.testing.assert_close(step.get(keys.MODE_PROBS), batched[keys.MODE_PROBS][:, t], rtol=1e-5, atol=1e-5)


def test_a_starting_track_reports_its_start_estimate_for_every_expert(data):
    """Scan 0: the first measurement, zero velocity; scan 1: the second, with the differenced velocity.
    A track whose first detection is missed starts one scan later; nothing else is an expert estimate."""
    net = IMMNet()
    z = data[keys.MEASUREMENTS][:2, :4].clone()
    z[1, 0] = math.nan
    carry = net.initial_carry(2)
    posts = []
    for t in range(4):
        carry = net.scan(carry, z[:, t])
        posts.append(carry.get(keys.EXPERT_POST))
    pos, vel = [0, 3, 6], [1, 4, 7]
    for b, t0 in ((0, 0), (1, 1)):
        first, second = posts[t0][b], posts[t0 + 1][b]  # [M, 9]
        torch.testing.assert_close(first[:, pos], z[b, t0].expand(4, 3))
        assert (first[:, vel] == 0).all()
        torch.testing.assert_close(second[:, pos], z[b, t0 + 1].expand(4, 3))
        torch.testing.assert_close(second[:, vel], (z[b, t0 + 1] - z[b, t0]).expand(4, 3))
    # from the third scan on the experts differ (each its own prediction and gain)
    assert (posts[3][0, 0] != posts[3][0, 1]).any()


def test_tracks_start_independently(data):
    """A track reset mid-stream behaves exactly like a track started on its own."""
    tracker = Tracker(IMMNet())
    z = data[keys.MEASUREMENTS][:2, :30]
    alone = tracker.track(z[1:2, 10:])[keys.STATE][0]
    tracker.reset(2)
    for t in range(30):
        out = tracker.step(z[:, t], reset=torch.tensor([False, t == 10]))
        if t >= 10:  # float32, and another batch composition: the BLAS sums differ in the last bits
            torch.testing.assert_close(out.get(keys.FUSED)[1], alone[t - 10], rtol=1e-4, atol=2e-3)


def test_predict_propagates_adaptive_experts_at_their_state_turn_rate():
    """Each expert's prior against the closed form of its own model (CV/CA: F x; CT: F_CT(w(x)) x)."""
    from immnet.motion import DEG, ct_matrix
    from immnet.stages.predict import Predict
    from tensordict import TensorDict

    ms = ModelSet.from_config("configs/model_sets/imm4-adaptive.yaml")
    base = torch.tensor([1e4, 150.0, 0.0, -5e3, 80.0, 0.0, 3e3, 2.0, 0.0], dtype=torch.float64)
    rates = torch.tensor([3.0, -6.0, 0.0, 20.0]) * DEG
    x = torch.stack([ct_matrix(w.item(), 1.0) @ base for w in rates])  # centripetal acceleration of rate w
    prior = Predict(ms)(TensorDict({keys.FUSED: x.float()}, batch_size=[4]))[keys.EXPERT_PRIOR].double()
    bounded = {2: rates.clamp(1 * DEG, 10 * DEG), 3: rates.clamp(-10 * DEG, -1 * DEG)}
    for b in range(4):
        torch.testing.assert_close(prior[b, 0], ms[0].F(1.0) @ x[b], rtol=1e-5, atol=1e-2)
        torch.testing.assert_close(prior[b, 1], ms[1].F(1.0) @ x[b], rtol=1e-5, atol=1e-2)
        for i in (2, 3):
            torch.testing.assert_close(prior[b, i], ct_matrix(bounded[i][b].item(), 1.0) @ x[b], rtol=1e-5, atol=1e-2)


@pytest.mark.parametrize("misses", [0, 1, 3])
def test_start_velocity_spans_the_missed_scans(misses):
    """A track whose second detection comes ``1 + misses`` scans after its first starts at the true
    velocity of a straight, noise-free flight (the difference over the time elapsed)."""
    net = IMMNet()
    v = torch.tensor([120.0, -80.0, 3.0])
    p0 = torch.tensor([1e4, 2e3, 5e3])
    carry = net.initial_carry(1)
    for t in range(misses + 2):
        detected = t in (0, misses + 1)
        z = (p0 + v * t)[None] if detected else torch.full((1, 3), float("nan"))
        carry = net.scan(carry, z)
    x = carry.get(keys.FUSED)[0]
    torch.testing.assert_close(x[[1, 4, 7]], v, rtol=1e-5, atol=1e-3)
    torch.testing.assert_close(x[[0, 3, 6]], p0 + v * (misses + 1), rtol=1e-6, atol=1e-2)


def test_stacked_layers_equal_one_torch_layer_per_expert():
    """Expert i of the stacked (expert-major) layers is nn.Linear / nn.GRUCell with weights W[i]."""
    torch.manual_seed(0)
    M, B = 3, 5
    lin, gru = StackedLinear(M, 7, 4).double(), StackedGRUCell(M, 7, 6).double()
    x, h = torch.randn(M, B, 7, dtype=torch.float64), torch.randn(M, B, 6, dtype=torch.float64)
    y, h_new = lin(x), gru(x, h)
    for i in range(M):
        ref = nn.Linear(7, 4).double()
        ref.weight.data, ref.bias.data = lin.weight[i].detach(), lin.bias[i].detach()
        torch.testing.assert_close(y[i], ref(x[i]), rtol=0, atol=1e-12)
        cell = nn.GRUCell(7, 6).double()
        for name in ("weight_ih", "weight_hh", "bias_ih", "bias_hh"):
            getattr(cell, name).data = getattr(gru, name)[i].detach()
        torch.testing.assert_close(h_new[i], cell(x[i], h[i]), rtol=0, atol=1e-12)


def test_stage_2_loss_is_the_papers_plus_the_own_mode_term(data):
    """gamma * MSE + (1 - gamma) * CE, plus expert_weight * each expert's loss on its own mode's scans,
    recomputed here scan by scan in float64 from the rollout's expert posteriors."""
    batch = _crop(data, 30)
    torch.manual_seed(0)
    paper, extra = Stage2Module(), Stage2Module(expert_weight=0.5)
    extra.net.load_state_dict(paper.net.state_dict())
    out, _ = paper.net.rollout(batch[keys.MEASUREMENTS])
    loss0, mse, ce, _ = paper.losses(out, batch)
    assert torch.allclose(loss0, 0.7 * mse + 0.3 * ce)
    loss1, mse1, ce1, own = extra.losses(out, batch)
    torch.testing.assert_close((mse1, ce1), (mse, ce))
    post, truth = out[keys.ROLLOUT_EXPERT_POST].double(), batch[keys.STATES].double()
    w = torch.tensor([1.0, 0.1, 0.02] * 3, dtype=torch.float64)
    modes = extra.net.model_set.modes.tolist()
    num = den = 0.0
    for b in range(truth.shape[0]):
        for t in range(truth.shape[1]):
            for i, m in enumerate(modes):
                if m == batch[keys.MODE][b, t]:
                    num += float(((post[b, t, i] - truth[b, t]) ** 2 * w).sum()) / float(batch[keys.R][b])
                    den += 1.0 / float(batch[keys.R][b])
    assert own.item() == pytest.approx(num / den, rel=1e-5)
    assert loss1.item() == pytest.approx(loss0.item() + 0.5 * num / den, rel=1e-5)
    with pytest.raises(ValueError, match="expert_weight"):
        Stage2Module(expert_weight=-1.0)


def test_stage_2_fine_tunes_from_a_whole_immnet(tmp_path):
    """``init_checkpoint`` starts from every weight of the shipped IMMNet; the Markov chain, set once on
    the network (issue 21, item 4), may change: the interaction mixes with it and the mode update predicts
    with the same transition; a checkpoint of another model set is refused."""
    path = REPO_ROOT / "immnet/pretrained/immnet.ckpt"
    raw = load_checkpoint(path)
    net = copy.deepcopy(raw["hyper_parameters"]["net"]) | {"p_stay": 0.9}
    module = Stage2Module(net=net, init_checkpoint=str(path))
    shipped = {k[len("net."):]: v for k, v in raw["state_dict"].items()  # the steps' copies are dropped on load
               if k.startswith("net.") and not k.endswith("log_pi") and not k.startswith(("net.step.", "net.expert_step."))}
    mine = module.net.state_dict()
    assert mine.keys() == shipped.keys()
    for k, v in shipped.items():
        assert torch.equal(mine[k], v), k
    # the interaction runs with the new p_stay: Pi's diagonal is 0.9, off-diagonal shares the rest
    Pi = module.net.interact.Pi.double()
    torch.testing.assert_close(Pi.diagonal(), torch.full((4,), 0.9, dtype=torch.float64), rtol=0, atol=1e-7)
    torch.testing.assert_close(Pi.sum(-1), torch.ones(4, dtype=torch.float64), rtol=0, atol=1e-6)
    assert module.net.classify.p_stay == 0.9
    # the mode update predicts with the transition the experts were mixed with, guarded per track
    td = module.net.initial_carry(3)
    td.set(keys.MEASUREMENT, torch.tensor([[5e3, 2e3, 3e3]] * 3))
    td = module.net.interact(td)
    assert td.get(keys.MODE_TRANSITION).shape == (3, 4, 4) and module.net.classify.reads_transition
    with pytest.raises(ValueError, match="does not match this IMMNet"):
        Stage2Module(net={"model_set": "configs/model_sets/imm4.yaml"}, init_checkpoint=str(path))
    with pytest.raises(ValueError, match="give one of .*not stage1_checkpoint and init_checkpoint"):
        Stage2Module(net=raw["hyper_parameters"]["net"], init_checkpoint=str(path), stage1_checkpoint=str(path))


def test_a_checkpoint_without_the_interval_input_starts_a_network_that_reads_it(tmp_path):
    """Widening (``widen_for_interval``): the shipped 1 s network loaded into one that reads each scan's interval
    (gain and classifier) gets a zero column for it and computes what the shipped one does, at irregular intervals
    too, until training moves that column; after a step the interval changes the estimates."""
    path = REPO_ROOT / "immnet/pretrained/immnet.ckpt"
    raw = load_checkpoint(path)
    net = copy.deepcopy(raw["hyper_parameters"]["net"])
    base = Stage2Module(net=net, init_checkpoint=str(path)).net
    net["gain"]["init_args"] = {**net["gain"].get("init_args", {}), "interval_input": True}
    net["classifier"]["init_args"] = {**net["classifier"].get("init_args", {}), "interval_input": True}
    wide = Stage2Module(net=net | {"interval_range": [0.5, 12.0]}, init_checkpoint=str(path)).net
    cols = wide.interval_columns()
    assert {k.split(".")[-2:][0] for k in cols} == {"fc7", "embed"} and set(cols.values()) == {6, 18}
    for name, col in cols.items():
        w = wide.state_dict()[name]
        assert torch.equal(w[..., col], torch.zeros_like(w[..., col]))
        assert torch.equal(torch.cat([w[..., :col], w[..., col + 1:]], -1), base.state_dict()[name])
    batch = generate(3, seed=4, spec=DataSpec(T=30, min_segment=10, dt=4.0, dt_jitter=3.5))
    z, intervals = batch[keys.MEASUREMENTS].float(), wide.intervals_for(batch)
    assert intervals is not None and float(intervals[:, 1:].std()) > 0.5
    base, wide, z, intervals = base.double(), wide.double(), z.double(), intervals.double()  # no float32 rounding
    with torch.no_grad():
        a, _ = base.rollout(z, intervals=intervals)
        b, _ = wide.rollout(z, intervals=intervals)
    torch.testing.assert_close(b[keys.STATE], a[keys.STATE], rtol=0, atol=1e-8)
    torch.testing.assert_close(b[keys.ROLLOUT_EXPERT_PROBS], a[keys.ROLLOUT_EXPERT_PROBS], rtol=0, atol=1e-10)
    with torch.no_grad():
        for name, col in cols.items():
            wide.get_parameter(name)[..., col] = 0.5
        c, _ = wide.rollout(z, intervals=intervals)
    assert float((c[keys.STATE] - a[keys.STATE]).abs().max()) > 0.1
    with pytest.raises(ValueError, match="does not match this IMMNet"):  # any other mismatch is still refused
        other = copy.deepcopy(net)
        other["classifier"]["init_args"]["d_model"] = 16
        Stage2Module(net=other, init_checkpoint=str(path))


def test_a_checkpoint_with_joint_modes_starts_a_network_with_modes_per_channel():
    """Widening (``widen_for_groups``): the shipped general network (one set of modes; trained in float32, its
    float64 buffers stored so rounded, which fine-tuning accepts) loaded into the same network with modes per channel
    gets its Transformer head's last layer once per channel, so that each channel starts with
    the joint correction of the mode update; every other weight loads as it is."""
    path = REPO_ROOT / "immnet/pretrained/immnet-general.ckpt"
    net = copy.deepcopy(load_checkpoint(path)["hyper_parameters"]["net"])
    base = Stage2Module(net=net, init_checkpoint=str(path)).net
    wide = Stage2Module(net=net | {"modes": "channel"}, init_checkpoint=str(path)).net
    rows = wide.group_rows()
    assert set(rows.values()) == {2} and {k.split(".", 1)[1] for k in rows} == {"head.2.weight", "head.2.bias"}
    own, joint = wide.state_dict(), base.state_dict()
    for name in own:
        if name in rows:
            assert torch.equal(own[name], torch.cat([joint[name]] * 2))
        else:
            assert torch.equal(own[name], joint[name]), name
    x = torch.randn(5, base.classify.head[0].in_features)
    with torch.no_grad():
        logits = wide.classify.head(x).unflatten(-1, (2, base.n_experts))
        torch.testing.assert_close(logits, base.classify.head(x).unsqueeze(1).expand(-1, 2, -1), rtol=0, atol=0)
        z = generate(2, seed=1, spec=DataSpec(T=25, min_segment=5))[keys.MEASUREMENTS].float()
        out, _ = wide.rollout(z)
    assert out[keys.ROLLOUT_EXPERT_PROBS].shape == (2, 25, 2, 4) and torch.isfinite(out[keys.STATE][:, 1:]).all()
    other = copy.deepcopy(net)  # a setting that builds another stored buffer (the filters' noise) is still refused
    other["gain"]["init_args"]["noise_std"] = [0.3, 0.2, 0.01, 0.002, 1e-05]
    with pytest.raises(ValueError, match=r"other settings than `net` gives: its buffers \['gain.Q_parts'\]"):
        Stage2Module(net=other, init_checkpoint=str(path))


def test_the_interaction_is_a_stage_slot_and_a_state_dict_names_each_weight_once():
    """Filter experts mix in a stage of their own, first in the step (``FilterInteraction``, with the gain's
    interaction, p_stay and guard); the steps are not submodules, so the state dict holds each weight once, under
    its stage's role, and a checkpoint that also holds the steps' indexed copies (the shipped files) loads."""
    from immnet.checkpoints import shipped
    from immnet.stages.filtering import FilterInteraction

    net = Tracker.pretrained("3dlast").net
    assert isinstance(net.step.module[1], FilterInteraction) and net.step.module[1] is net.interact  # after TrackStart
    assert net.interact.interaction == "imm" and net.interact.guard is not None and net.interact.p_stay == 0.999
    assert [type(m).__name__ for m in net.expert_step.module][1] == "FilterInteraction"
    assert net.expert_step.module[1].interaction == "fused"  # experts alone start from their own posterior
    sd = net.state_dict()
    assert not any(k.startswith(("step.", "expert_step.")) for k in sd)
    named = [n for n, _ in net.named_parameters(remove_duplicate=False)]
    assert len(named) == len({id(p) for p in net.parameters()})  # no parameter under two names
    legacy = load_checkpoint(shipped("3dlast"))["state_dict"]
    assert any(k.startswith("net.step.module.") for k in legacy)  # written with the copies; loaded above
    assert {k[len("net."):] for k in legacy  # log_pi: a buffer older files hold, rebuilt from p_stay
            if not k.startswith(("net.step.", "net.expert_step.")) and not k.endswith("log_pi")} == set(sd)
    paper = IMMNet()  # the paper's gain experts have no interaction slot: predict takes the fused estimate
    assert paper.interact is None and type(paper.step.module[1]).__name__ == "Predict"


@pytest.mark.parametrize("irregular", [False, True], ids=["nominal", "intervals"])
def test_track_starts_run_through_the_step(irregular):
    """A track starts inside the step (``immnet.stages.start``): ``TrackStart`` first, ``JoinStarts`` last. Run as
    the bare ``TensorDictSequential`` scan by scan, the start estimates are the closed forms (first detection
    ``[z, 0, 0]``, second ``[z, (z - z_first) / elapsed, 0]`` with ``elapsed`` the time since the first detection,
    missed scans counted), a track with no detection keeps its carry, the carry holds only the stages' keys, and
    the rollout is the same loop."""
    from immnet.stages.start import JoinStarts, TrackStart

    net = IMMNet(model_set="configs/model_sets/imm4-adaptive.yaml",
                 gain={"class_path": "immnet.stages.filtering.FilterGain", "init_args": {"interaction": "imm"}},
                 classifier={"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"from_experts": True}},
                 dt=1.0).double().eval()
    assert isinstance(net.step.module[0], TrackStart) and isinstance(net.step.module[-1], JoinStarts)
    assert isinstance(net.expert_step.module[0], TrackStart) and isinstance(net.expert_step.module[-1], JoinStarts)
    g = torch.Generator().manual_seed(4)
    z = 1000.0 * torch.randn(4, 5, 3, generator=g, dtype=torch.float64)
    z[1, 1] = z[1, 2] = z[2, 0] = float("nan")  # track 1 misses twice before its second detection, 2 its first
    z[3] = float("nan")  # track 3: none
    gaps = (torch.tensor([[1.0, 2.0, 3.0, 0.5, 4.0]], dtype=torch.float64).expand(4, 5) if irregular
            else torch.ones(4, 5, dtype=torch.float64))
    carry = net.initial_carry(4, dtype=torch.float64)
    states = []
    with torch.no_grad():
        for t in range(5):
            td = carry.copy()
            td.set(keys.MEASUREMENT, z[:, t])
            if irregular:
                td.set(keys.INTERVAL, gaps[:, t])
            carry = net.step(td)
            if irregular:
                carry.del_(keys.INTERVAL)
            states.append(carry.get(keys.FUSED))
            assert "start" not in carry.keys()
            assert set(carry.exclude(keys.MEASUREMENT).keys(True, True)) >= set(net.carry_keys)
        ref, _ = net.rollout(z, intervals=gaps if irregular else None)
    x = torch.stack(states, 1)
    torch.testing.assert_close(x, ref[keys.STATE], rtol=0, atol=0)

    def start(zi, v=None):
        out = torch.zeros(9, dtype=torch.float64)
        out[0::3] = zi
        if v is not None:
            out[1::3] = v
        return out

    torch.testing.assert_close(x[0, 0], start(z[0, 0]))
    torch.testing.assert_close(x[0, 1], start(z[0, 1], (z[0, 1] - z[0, 0]) / gaps[0, 1]))
    for t in (0, 1, 2):  # track 1: its first detection held while it waits for the second
        torch.testing.assert_close(x[1, t], start(z[1, 0]))
    torch.testing.assert_close(x[1, 3], start(z[1, 3], (z[1, 3] - z[1, 0]) / gaps[1, 1:4].sum()))
    torch.testing.assert_close(x[2, 1], start(z[2, 1]))
    torch.testing.assert_close(x[2, 2], start(z[2, 2], (z[2, 2] - z[2, 1]) / gaps[2, 2]))
    assert (x[3] == 0).all() and (carry.get(keys.AGE) == torch.tensor([2, 2, 2, 0])).all()
    assert not torch.equal(x[0, 2], start(z[0, 2]))  # from the third detection on, the filters' estimate
    # tracks that have all started: the step without the start's two stages (what scan runs for them) is the step
    running = carry[:3].exclude(keys.MEASUREMENT)
    td = running.copy()
    td.set(keys.MEASUREMENT, z[:3, -1] + 10.0)
    with torch.no_grad():
        whole, short = net.step(td.copy()), net.running_step(td.copy())
    assert set(whole.keys(True, True)) == set(short.keys(True, True))
    for key in whole.keys(True, True):
        assert torch.equal(whole.get(key), short.get(key)), key
