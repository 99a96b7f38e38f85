"""The clairvoyant KF is a bound: no IMM configuration beats it on generated 3D-LAST data."""

import pytest
import torch

from immnet import keys
from immnet.config import REPO_ROOT, build
from immnet.evaluation.metrics import position_error, rmse
from immnet.filters import ClairvoyantKF

IMM_CONFIGS = ["imm-accurate", "imm-min", "imm-max", "imm-tuned"]


@pytest.fixture(scope="module")
def data():
    generate = pytest.importorskip("immnet.data.generate").generate
    return generate(200, seed=4242)


@pytest.fixture(scope="module")
def bound(data):
    return rmse(position_error(ClairvoyantKF().track(data)[keys.STATE], data[keys.STATES]))["avg"]


def test_clairvoyant_beats_raw_measurements(data, bound):
    raw = data[keys.MEASUREMENTS].repeat_interleave(3, dim=-1)
    assert bound < 0.7 * rmse(position_error(raw, data[keys.STATES]))["avg"]


@pytest.mark.slow
@pytest.mark.parametrize("name", IMM_CONFIGS, ids=IMM_CONFIGS)
def test_no_imm_beats_the_clairvoyant_bound(data, bound, name):
    path = REPO_ROOT / "configs" / "methods" / f"{name}.yaml"
    if not path.exists():
        pytest.skip(f"{path.name} not written yet (immnet.evaluation.tuning.tune_imm)")
    with torch.no_grad():
        imm = rmse(position_error(build(path).track(data)[keys.STATE], data[keys.STATES]))["avg"]
    assert bound < imm, f"{name} {imm:.3f} m beat the clairvoyant bound {bound:.3f} m"


def test_switch_clairvoyant_told_the_turn_rate_is_the_bound():
    """Where every turn flies at 6 deg/s and the prior is exactly that, estimating the rate is knowing
    it: the switch-clairvoyant EKF of [x, w] equals the bound scan by scan (missed detections too)."""
    from immnet.data.generate import generate
    from immnet.data.spec import DataSpec
    from immnet.filters import SwitchClairvoyantKF

    data = generate(40, seed=7, spec=DataSpec(T=200, min_segment=40, turn_rate_min_deg=6.0, turn_rate_max_deg=6.0,
                                               bound_turn_rate_deg=6.0))
    data[keys.MEASUREMENTS][3, 50:53] = float("nan")
    bound = ClairvoyantKF().track(data)[keys.STATE]
    told = SwitchClairvoyantKF(turn_prior_deg=(6.0, 0.0)).track(data)[keys.STATE]
    torch.testing.assert_close(told, bound, rtol=1e-9, atol=1e-7)


def test_switch_clairvoyant_lies_between_the_bound_and_raw_measurements(data, bound):
    from immnet.filters import SwitchClairvoyantKF

    switch = rmse(position_error(SwitchClairvoyantKF().track(data)[keys.STATE], data[keys.STATES]))["avg"]
    raw = rmse(position_error(data[keys.MEASUREMENTS].repeat_interleave(3, dim=-1), data[keys.STATES]))["avg"]
    assert bound < switch < 0.7 * raw


SCAN_SPECS = {
    "1s": dict(T=150, min_segment=40, p_miss=0.05),
    "4.5-5.5s": dict(T=60, min_segment=4, dt=5.0, dt_jitter=0.5, p_miss=0.05),
}


def _oracle_data(scans: str):
    """Generated tracks with missed detections, a track first detected at scan 3, and (for the switch reference)
    turns whose labelled rate changes within the turn: the truth's restarts, which the generator draws rarely."""
    from immnet.data.generate import generate
    from immnet.data.spec import DataSpec
    from immnet.filters import SwitchClairvoyantKF
    from immnet.motion import CT_POS

    spec = DataSpec(**SCAN_SPECS[scans])
    data = generate(12, seed=8, spec=spec)
    data[keys.MEASUREMENTS][3, 20:25] = float("nan")
    data[keys.MEASUREMENTS][5, 1] = float("nan")  # a missed detection right after the start
    data[keys.MEASUREMENTS][7, :3] = float("nan")  # a track first detected at scan 3
    mode, rate = data[keys.MODE], data[keys.TURN_RATE]
    for b in range(mode.shape[0]):  # a new rate in the middle of each track's first turn of 6 scans or more
        turning = (mode[b] >= CT_POS).nonzero().flatten().tolist()
        runs = [t for t in turning if t + 5 in turning and all(mode[b, t + k] == mode[b, t] for k in range(6))]
        if runs:
            t = runs[0] + 3
            rate[b, t:] = torch.where(mode[b, t:] == mode[b, t], rate[b, t:] * 1.3, rate[b, t:])
    assert SwitchClairvoyantKF.restarts(mode, rate).any(1).sum() >= 3
    return spec, data


@pytest.mark.parametrize("scans", list(SCAN_SPECS))
@pytest.mark.parametrize("kind", ["clairvoyant", "clairvoyant-switch"])
def test_the_clairvoyant_filters_are_configurations_of_the_step(kind, scans):
    """Issue 21, item 1, for the bound and the switch reference: each equals its ``network()``, IMMNet's step with
    nothing learned and an oracle (the truth's modes in the classifier's slot, ``TrueModeUpdate``; the bound's turn
    told the truth's rate, ``FilterGain(turn_rate="data")``; the switch reference's turns estimating their rate
    unbounded and re-entered where the truth's rate changes within a turn, ``restart="data"``), to 1e-9 of each
    track's scale (Joseph's covariance update and the standard one), at 1 s and at irregular 4.5-5.5 s scans, from
    each track's first detection; its modes are the truth's there, one-hot."""
    from immnet.filters import SwitchClairvoyantKF

    from immnet.filters.methods import build_method

    spec, data = _oracle_data(scans)
    method = build_method(kind)  # the registry's, told the data's statistics as `immnet evaluate` tells it
    assert isinstance(method, ClairvoyantKF if kind == "clairvoyant" else SwitchClairvoyantKF)
    method.configure({"spec": spec.to_dict()})
    net = method.network()
    intervals = net.intervals_for(data)
    assert (intervals is None) == (scans == "1s")
    with torch.no_grad():
        out, _ = net.rollout(data[keys.MEASUREMENTS].double(), r=data[keys.R].double(), intervals=intervals,
                             truth=method.truth(data))
    ours = method.track(data)[keys.STATE]
    seen = ~torch.isnan(ours[..., :1])
    assert not seen[7, :3].any() and seen[7, 3:].all()
    scale = torch.nan_to_num(ours).abs().amax((1, 2), keepdim=True)
    assert ((out[keys.STATE] - ours).abs() <= 1e-9 * scale)[seen.expand_as(ours)].all()
    probs = out[keys.ROLLOUT_EXPERT_PROBS]
    truth = net.classify.expert_of[data[keys.MODE]]
    onehot = torch.nn.functional.one_hot(truth, net.n_experts).double()
    assert torch.equal(probs[seen[..., 0]], onehot[seen[..., 0]])  # from the first detection on (uniform before)


def test_an_oracle_step_without_its_truth_or_with_a_mode_it_lacks_is_refused():
    """A step that reads the truth is refused without it (the input named) or with a scan without a label, and the
    oracle refuses a model set that has no expert for a data mode, a mapping of the wrong length and modes per
    group."""
    from immnet.motion import ModelSet
    from immnet.stages import TrueModeUpdate
    from immnet.stages.filtering import FilterGain

    spec, data = _oracle_data("1s")
    net = ClairvoyantKF(spec=spec).network()
    z = data[keys.MEASUREMENTS].double()
    with pytest.raises(ValueError, match=r"truth's 'mode'.*truth="):
        net.rollout(z, r=data[keys.R].double())
    with pytest.raises(ValueError, match=r"truth's 'turn_rate'"):
        net.rollout(z, r=data[keys.R].double(), truth={keys.TRUE_MODE: data[keys.MODE]})
    unlabelled = data[keys.MODE].clone()
    unlabelled[2, 30:] = -1  # a scan without a label (real flights)
    with pytest.raises(ValueError, match="truth's mode at every scan"):
        net.rollout(z, r=data[keys.R].double(), truth={keys.TRUE_MODE: unlabelled, keys.TRUE_TURN_RATE: data[keys.TURN_RATE]})
    cv_ca = ModelSet.from_config([{"class_path": "immnet.motion.ConstantVelocity"},
                                  {"class_path": "immnet.motion.ConstantAcceleration"}])
    with pytest.raises(ValueError, match="data mode 'ct\\+' has no expert"):
        TrueModeUpdate(cv_ca)
    with pytest.raises(ValueError, match="one expert index"):
        TrueModeUpdate(cv_ca, experts=[0, 1, 2, 0])
    with pytest.raises(ValueError, match="modes='joint'"):
        TrueModeUpdate(cv_ca, experts=[0, 1, 0, 0], modes="axis")
    with pytest.raises(ValueError, match="turn_rate must be"):
        FilterGain(cv_ca, turn_rate="truth")
    with pytest.raises(ValueError, match="needs interaction='imm'"):
        FilterGain(cv_ca, restart="data")


@pytest.mark.parametrize("kind", ["clairvoyant", "clairvoyant-switch"])
def test_an_oracle_step_traces_as_one_graph_and_gives_the_eager_outputs(kind):
    """Issue 21, item 1: an oracle's step, as every step, has no data-dependent branch under ``torch.compile``
    (``fullgraph=True``; the ``eager`` backend runs the traced graph, no C++ compiler needed; the check of the
    truth's labels is eager only) and the graph's outputs are the eager step's."""
    from immnet.filters.methods import build_method

    spec, data = _oracle_data("4.5-5.5s")
    method = build_method(kind)
    method.configure({"spec": spec.to_dict()})
    net = method.network()
    z, r, truth = data[keys.MEASUREMENTS].double(), data[keys.R].double(), method.truth(data)
    intervals = net.intervals_for(data)
    with torch.no_grad():
        carry = net.initial_carry(z.shape[0], dtype=torch.float64)
        for t in range(6):
            carry = net.scan(carry, z[:, t], interval=intervals[:, t], r=r, truth={k: v[:, t] for k, v in truth.items()})
        td = carry.copy()
        td.set(keys.MEASUREMENT, z[:, 6])
        td.set(keys.INTERVAL, intervals[:, 6])
        td.set(keys.R, r)
        for key, value in truth.items():
            td.set(key, value[:, 6])
        torch._dynamo.reset()
        traced = torch.compile(net.step, fullgraph=True, backend="eager")(td.copy())
        eager = net.step(td.copy())
    for key in eager.keys(True, True):
        torch.testing.assert_close(traced.get(key), eager.get(key), rtol=1e-9, atol=1e-9, equal_nan=True, msg=str(key))
