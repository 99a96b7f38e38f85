"""Issue 21, item 3: stages that tell the truth.

Every stage of every IMMNet configuration that changes a stage's keys is run on a real scan's
TensorDict (an IMMNet rollout up to that scan, then the stages before it), on
``td.select(*stage.in_keys)`` alone: it must not miss a key, it must write exactly its ``out_keys``
(a key is written when it is new or its tensor changed identity or value), it must give the same outputs there as on the whole scan (it reads nothing else), and every key it
declares to read must matter (without it the stage fails or gives other outputs).
"""

import pytest
import torch
from tensordict import TensorDict
from tensordict.utils import unravel_key

from immnet import keys
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.stages import IMMNet

FILTERING = "immnet.stages.filtering."
CONFIGS = {
    "kalmannet+transformer": {},
    "kalmannet-adaptive-ct": {"model_set": "configs/model_sets/imm4-adaptive.yaml"},
    "analytic+bayes": {"model_set": "configs/model_sets/imm3.yaml",
                       "gain": {"class_path": "immnet.stages.AnalyticGain"},
                       "classifier": {"class_path": "immnet.stages.BayesianModeUpdate"}},
    "analytic+uniform": {"gain": {"class_path": "immnet.stages.AnalyticGain"},
                         "classifier": {"class_path": "immnet.stages.UniformMix"}},
    "filter-fused+bayes-transformer": {"model_set": "configs/model_sets/imm4-adaptive.yaml",
                                       "gain": {"class_path": FILTERING + "FilterGain"},
                                       "classifier": {"class_path": "immnet.stages.BayesTransformerClassifier"}},
    "filter-imm-guard+bayes-experts": {
        "model_set": "configs/model_sets/imm4-adaptive.yaml",
        "gain": {"class_path": FILTERING + "FilterGain", "init_args": {"interaction": "imm", "guard": True}},
        "classifier": {"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"from_experts": True}}},
    "kalmannet-filter-imm-guard+bayes-transformer": {
        "model_set": "configs/model_sets/imm4-adaptive.yaml",
        "gain": {"class_path": FILTERING + "KalmanNetFilterGain",
                 "init_args": {"interaction": "imm", "p_stay": 0.999, "guard": True}},
        "classifier": {"class_path": "immnet.stages.BayesTransformerClassifier", "init_args": {"p_stay": 0.999}}},
    "kalmannet-filter-imm-guard-adapt+bayes-guarded": {
        "model_set": "configs/model_sets/imm4-adaptive.yaml",
        "gain": {"class_path": FILTERING + "KalmanNetFilterGain",
                 "init_args": {"interaction": "imm", "guard": True, "adapt": True}},
        "classifier": {"class_path": "immnet.stages.BayesianModeUpdate"}},
    "kalmannet-filter-imm+transformer": {
        "model_set": "configs/model_sets/imm4-adaptive.yaml",
        "gain": {"class_path": FILTERING + "KalmanNetFilterGain", "init_args": {"interaction": "imm"}}},
    "kalmannet-filter-imm-interval+bayes-transformer-consistency": {  # the general network's shape
        "model_set": "configs/model_sets/imm4-adaptive.yaml", "guard": False, "interval_range": [0.5, 12.0],
        "cov_consistency": 0.05,
        "gain": {"class_path": FILTERING + "KalmanNetFilterGain", "init_args": {"interaction": "imm", "interval_input": True}},
        "classifier": {"class_path": "immnet.stages.BayesTransformerClassifier", "init_args": {"interval_input": True}}},
    "kalmannet-filter-fused-adapt+uniform": {
        "model_set": "configs/model_sets/imm4-adaptive.yaml",
        "gain": {"class_path": FILTERING + "KalmanNetFilterGain", "init_args": {"adapt": True}},
        "classifier": {"class_path": "immnet.stages.UniformMix"}},
    "single-ca": {"model_set": [{"class_path": "immnet.motion.ConstantAcceleration"}]},
    "filter-linear-imm+bayes-experts": {  # a linear IMM as IMMNet with nothing learned (IMMTracker.network)
        "model_set": "configs/model_sets/imm6.yaml", "p_stay": 0.8, "start_detections": 1,
        "gain": {"class_path": FILTERING + "FilterGain", "init_args": {
            "interaction": "imm", "onset": False, "model_noise": 0.5, "r": 5.0, "start_acc_std": 10.0}},
        "classifier": {"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"from_experts": True}}},
    "filter-linear-imm-told-r+bayes-experts": {  # the same told each track's r (the real-flight IMMs' r: data)
        "model_set": "configs/model_sets/imm3.yaml", "p_stay": 0.9, "start_detections": 1,
        "gain": {"class_path": FILTERING + "FilterGain", "init_args": {
            "interaction": "imm", "onset": False, "model_noise": [0.7, 0.35, 0.7], "r": "data", "start_acc_std": 10.0}},
        "classifier": {"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"from_experts": True}}},
    "kalmannet-filter-per-axis-told-r+bayes-transformer": {  # modes per axis over CV and CA (the decoupled IMM's)
        "model_set": [{"class_path": "immnet.motion.ConstantVelocity"}, {"class_path": "immnet.motion.ConstantAcceleration"}],
        "p_stay": 0.98, "modes": "axis",
        "gain": {"class_path": FILTERING + "KalmanNetFilterGain", "init_args": {
            "interaction": "imm", "onset": False, "model_noise": [0.4, 0.35], "r": "data", "start_acc_std": 10.0}},
        "classifier": {"class_path": "immnet.stages.BayesTransformerClassifier"}},
    "kalmannet-filter-per-axis-correction+bayes-transformer": {  # with a learned state correction (its own key)
        "model_set": [{"class_path": "immnet.motion.ConstantVelocity"}, {"class_path": "immnet.motion.ConstantAcceleration"}],
        "p_stay": 0.98, "modes": "axis",
        "gain": {"class_path": FILTERING + "KalmanNetFilterGain", "init_args": {
            "interaction": "imm", "onset": False, "model_noise": [0.4, 0.35], "start_acc_std": 10.0,
            "state_correction": [2.0, 1.0, 0.5]}},
        "classifier": {"class_path": "immnet.stages.BayesTransformerClassifier"}},
    "filter-per-axis-told-r+bayes-experts+output-correction": {  # real-singer-output's shape: a learned output correction
        "model_set": [{"class_path": "immnet.motion.ConstantVelocity"}, {"class_path": "immnet.motion.ConstantAcceleration"}],
        "p_stay": 0.98, "modes": "axis", "start_detections": 1,
        "gain": {"class_path": FILTERING + "FilterGain", "init_args": {
            "interaction": "imm", "onset": False, "model_noise": [0.4, 0.35], "r": "data", "start_acc_std": 10.0}},
        "classifier": {"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"from_experts": True}},
        "correction": {"class_path": "immnet.stages.correct.OutputCorrection", "init_args": {"hidden": 8}}},
    "filter-per-axis+bayes-experts+correction-ensemble": {  # real-5s's shape: several corrections on one filter
        "model_set": [{"class_path": "immnet.motion.ConstantVelocity"}, {"class_path": "immnet.motion.ConstantAcceleration"}],
        "p_stay": 0.98, "modes": "axis", "start_detections": 1, "interval_range": [4.5, 5.5],
        "gain": {"class_path": FILTERING + "FilterGain", "init_args": {
            "interaction": "imm", "onset": False, "model_noise": [0.4, 0.35], "r": None, "start_acc_std": 10.0}},
        "classifier": {"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"from_experts": True}},
        "correction": {"class_path": "immnet.stages.correct.CorrectionEnsemble",
                       "init_args": {"members": 3, "hidden": 8}}},
    "kalmannet-filter-per-channel+bayes-transformer": {  # modes per channel over CV, CA and turns estimating their rate
        "model_set": "configs/model_sets/imm4-adaptive.yaml", "guard": False, "modes": "channel",
        "interval_range": [0.5, 12.0],
        "gain": {"class_path": FILTERING + "KalmanNetFilterGain", "init_args": {"interaction": "imm", "interval_input": True}},
        "classifier": {"class_path": "immnet.stages.BayesTransformerClassifier", "init_args": {"interval_input": True}}},
    "filter-told-turn-rate+true-modes": {  # the clairvoyant bound's configuration (ClairvoyantKF.network)
        "model_set": [{"class_path": "immnet.motion.ConstantVelocity"}, {"class_path": "immnet.motion.ConstantAcceleration"},
                      {"class_path": "immnet.motion.AdaptiveTurn"}], "p_stay": 0.5, "start_detections": 1,
        "gain": {"class_path": FILTERING + "FilterGain", "init_args": {
            "interaction": "imm", "model_noise": 0.2, "r": "data", "start_acc_std": [10.0, None, 10.0],
            "turn_rate": "data"}},
        "classifier": {"class_path": "immnet.stages.TrueModeUpdate"}},
    "filter-free-turn-rate-restart+true-modes": {  # the switch reference's (SwitchClairvoyantKF.network)
        "model_set": "configs/model_sets/imm4-adaptive.yaml", "p_stay": 0.5, "start_detections": 1,
        "gain": {"class_path": FILTERING + "FilterGain", "init_args": {
            "interaction": "imm", "model_noise": 0.2, "r": "data", "turn_rate": "free", "restart": "data"}},
        "classifier": {"class_path": "immnet.stages.TrueModeUpdate"}},
}
# (configuration, experts alone): stage 1 runs each expert alone (``IMMNet.expert_step``)
CASES = [(name, False) for name in CONFIGS if name != "single-ca"] + [
    (name, True) for name in ("kalmannet+transformer", "filter-fused+bayes-transformer",
                              "kalmannet-filter-imm-guard+bayes-transformer",
                              "kalmannet-filter-imm-guard-adapt+bayes-guarded", "single-ca",
                              "kalmannet-filter-per-axis-correction+bayes-transformer")
]
SCANS = 6  # the scan the stages are checked on: every track has started and run a few learned steps


@pytest.fixture(scope="module")
def data():
    td = generate(6, seed=3, spec=DataSpec(T=SCANS + 1, min_segment=1, n_segments=1))
    z = td[keys.MEASUREMENTS].float()
    # at the scan checked, tracks in every state of a start (``immnet.stages.start``): track 0's first
    # detection, track 1's second, track 2 misses its second, track 3 has none yet; tracks 4 and 5 run
    z[0, :SCANS] = z[1, : SCANS - 1] = z[2, : SCANS - 1] = z[3] = float("nan")
    z[2, SCANS] = float("nan")
    return z


def _net(name: str) -> IMMNet:
    torch.manual_seed(0)
    return IMMNet(**CONFIGS[name])


def _scan_inputs(net: IMMNet, z: torch.Tensor, alone: bool, interval: float | None = None):
    """The stages of one scan, each with the TensorDict it receives in a real rollout (``interval``: every scan's,
    carried by the step as ``("interval")``)."""
    if alone:
        z = z.unsqueeze(1).expand(-1, net.n_experts, -1, -1)
    gaps = None if interval is None else torch.full((z.shape[0], SCANS), interval)
    with torch.no_grad():
        _, carry = net.rollout(z[..., :SCANS, :], experts_alone=alone, intervals=gaps, **_inputs(net, z.shape[0], SCANS))
    td = carry.copy()
    td.set(keys.MEASUREMENT, z[..., SCANS, :])
    for key, value in _scan_inputs_at(net, z.shape[0], SCANS).items():
        td.set(key, value)
    if interval is not None:
        td.set(keys.INTERVAL, torch.full((z.shape[0],), interval))
    step = net.expert_step if alone else net.step
    for stage in step.module:
        yield stage, td.copy()
        with torch.no_grad():
            td = stage(td)


def _scan_inputs_at(net: IMMNet, B: int, t: int) -> dict:
    """The step's inputs beside the measurement at scan ``t`` (``immnet.stages.start.STEP_INPUTS``), where a stage
    reads them: each track's measurement std (a filter gain told it, ``r="data"``), an oracle's truth (a data mode,
    turn rate and restart that change from scan to scan)."""
    b = torch.arange(B)
    values = {keys.R: torch.linspace(2.0, 6.0, B), keys.TRUE_MODE: (b + t) % 4,
              keys.TRUE_TURN_RATE: 0.05 * (-1.0) ** (b + t), keys.TRUE_RESTART: (b + t) % 3 == 0}
    return {key: values[key] for key in net.start.inputs}


def _inputs(net: IMMNet, B: int, T: int) -> dict:
    """``rollout``'s keyword arguments for the step's inputs over scans ``0..T-1`` (``_scan_inputs_at``)."""
    scans = [_scan_inputs_at(net, B, t) for t in range(T)]
    out = {"r": scans[0][keys.R]} if keys.R in scans[0] else {}
    truth = {k: torch.stack([s[k] for s in scans], 1) for k in scans[0] if k != keys.R}
    return out | ({"truth": truth} if truth else {})


def _leaves(td: TensorDict) -> dict:
    return {unravel_key(k): v for k, v in td.items(True, True)}


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and bool(((a == b) | (a.isnan() & b.isnan())).all())


def _owner(leaf, declared):
    """The declared key a leaf lies under (a key, or a prefix of it: a nested TensorDict), or None."""
    for key in declared:
        key_t = (key,) if isinstance(key, str) else key
        leaf_t = (leaf,) if isinstance(leaf, str) else leaf
        if leaf_t[: len(key_t)] == key_t:
            return key
    return None


def _written(stage, td: TensorDict) -> tuple[dict, set]:
    """Run ``stage`` on ``td``; its outputs and the leaves it wrote (new, re-set or changed in place)."""
    before = _leaves(td)
    values = {k: v.clone() for k, v in before.items()}
    with torch.no_grad():
        out = stage(td)
    after = _leaves(out)
    written = {k for k, v in after.items() if k not in before or v is not before[k] or not _same(v, values[k])}
    return after, written


@pytest.mark.parametrize("name,alone", CASES, ids=[f"{n}{'-alone' if a else ''}" for n, a in CASES])
def test_every_stage_reads_and_writes_exactly_its_declared_keys(name, alone, data):
    net = _net(name)
    for stage, td in _scan_inputs(net, data, alone):
        what = f"{type(stage).__name__} ({name}{', experts alone' if alone else ''})"
        missing = [k for k in stage.in_keys if k not in td.keys(True)]
        assert not missing, f"{what} declares inputs {missing} that nothing before it provides"
        try:
            out, written = _written(stage, td.select(*stage.in_keys))
        except Exception as err:  # tensordict's get of a missing key gives None: any error
            pytest.fail(f"{what} fails on its declared inputs alone (it reads a key it does not declare): {err!r}")
        full, _ = _written(stage, td.copy())
        other = sorted(str(k) for k in out if not _same(out[k], full[k]))
        assert not other, f"{what} gives other {other} on its declared inputs than on the whole scan: it reads more"
        declared = [unravel_key(k) for k in stage.out_keys]
        undeclared = sorted(str(k) for k in written if _owner(k, declared) is None)
        assert not undeclared, f"{what} writes {undeclared}, not in its out_keys {declared}"
        unwritten = [k for k in declared if not any(_owner(w, [k]) is not None for w in written)]
        assert not unwritten, f"{what} declares outputs {unwritten} it does not write"
        for key in stage.in_keys:
            rest = [k for k in stage.in_keys if k != key]
            assert _needs(stage, td.select(*rest), out, declared) or _needs(
                stage, _perturbed(td.select(*stage.in_keys), key), out, declared
            ), f"{what} declares the input {key} but gives the same outputs without it or with it changed"


@pytest.mark.parametrize("name,alone", CASES, ids=[f"{n}{'-alone' if a else ''}" for n, a in CASES])
def test_with_the_scan_interval_every_stage_writes_exactly_its_declared_keys(name, alone, data):
    """Issue 22: where the step carries each scan's interval (``("interval")``, optional: absent, the stages
    use the network's ``dt``), a stage given its declared inputs and the interval writes exactly its
    ``out_keys``, and a rollout at intervals equal to ``dt`` is the rollout without them (float32 rounding),
    one at 2 s is not."""
    net = _net(name)
    for stage, td in _scan_inputs(net, data, alone, interval=2.0):
        what = f"{type(stage).__name__} ({name}{', experts alone' if alone else ''})"
        out, written = _written(stage, td.select(*stage.in_keys, keys.INTERVAL))
        declared = [unravel_key(k) for k in stage.out_keys]
        extra = sorted(str(k) for k in written if _owner(k, declared) is None and k != keys.INTERVAL)
        assert not extra, f"{what} writes {extra} with the interval, not in its out_keys {declared}"
    z = data.unsqueeze(1).expand(-1, net.n_experts, -1, -1) if alone else data
    with torch.no_grad():
        inputs = _inputs(net, z.shape[0], z.shape[-2])
        plain = net.rollout(z, experts_alone=alone, **inputs)[0][keys.STATE]
        same = net.rollout(z, experts_alone=alone, intervals=torch.full(z.shape[:1] + z.shape[-2:-1], 1.0), **inputs)[0][keys.STATE]
        other = net.rollout(z, experts_alone=alone, intervals=torch.full(z.shape[:1] + z.shape[-2:-1], 2.0), **inputs)[0][keys.STATE]
    torch.testing.assert_close(same, plain, rtol=1e-5, atol=1e-2)
    assert (other - plain).abs().max() > 1.0


def _needs(stage, td, out, declared) -> bool:
    """Whether ``stage`` on ``td`` fails or gives other outputs than ``out``."""
    try:
        other, _ = _written(stage, td)
    except Exception:
        return True
    return any(k not in other or not _same(out[k], other[k]) for k in out if _owner(k, declared) is not None)


def _perturbed(td: TensorDict, key) -> TensorDict:
    """``td`` with the leaves under ``key`` moved (floats by a quarter of their size plus one, NaN to 1,
    integers by one): for a key whose value in the scan checked happens not to matter (zeros, say)."""
    td = td.copy()
    for leaf, v in _leaves(td).items():
        if _owner(leaf, [unravel_key(key)]) is not None:
            moved = torch.nan_to_num(v, nan=1.0) + 0.25 * (1.0 + v.abs()) if v.is_floating_point() else v + 1
            td.set(leaf, torch.nan_to_num(moved, nan=1.0))
    return td


def _renamed(key):
    return ("renamed", *((key,) if isinstance(key, str) else key))


@pytest.mark.parametrize("name,alone", CASES, ids=[f"{n}{'-alone' if a else ''}" for n, a in CASES])
def test_set_keys_renames_what_every_stage_reads_and_writes(name, alone, data):
    """``set_keys`` (TorchRL's): every key of a stage moved under ``"renamed"``; the stage reads and
    writes the new names, gives the outputs of the default names, and leaves a default-named key
    of the TensorDict that is no longer its own alone."""
    from immnet.stages.base import KEY_NAMES

    by_key = {v: n for n, v in KEY_NAMES.items()}
    for stage, td in _scan_inputs(_net(name), data, alone):
        inputs = td.select(*stage.in_keys)
        out, _ = _written(stage, inputs.copy())
        default_in, default_out = [unravel_key(k) for k in stage.in_keys], [unravel_key(k) for k in stage.out_keys]
        mine = dict.fromkeys(default_in + default_out)
        stage.set_keys(**{by_key[k]: _renamed(k) for k in mine})
        assert [unravel_key(k) for k in stage.in_keys] == [_renamed(k) for k in default_in]
        assert [unravel_key(k) for k in stage.out_keys] == [_renamed(k) for k in default_out]
        moved = TensorDict({_renamed(k): v for k, v in _leaves(inputs).items()}, batch_size=inputs.batch_size)
        decoy = torch.full((inputs.batch_size[0], 1), 7.0)
        moved.set("measurement" if keys.MEASUREMENT not in mine else ("fused", "state"), decoy)
        result = _leaves(stage(moved))
        for k, v in out.items():
            if _owner(k, default_out) is not None:
                assert _same(result[_renamed(k)], v), (type(stage).__name__, k)
        assert [k for k in result if k[0] != "renamed"] == [k for k in _leaves(moved) if k[0] != "renamed"]
        assert all(result[k] is decoy for k in result if k[0] != "renamed")
        stage.set_keys(**{by_key[k]: k for k in mine})  # back to the defaults
        assert [unravel_key(k) for k in stage.in_keys] == default_in


def test_set_keys_refuses_a_key_the_stage_does_not_have():
    net = _net("kalmannet+transformer")
    with pytest.raises(ValueError, match="not one of its keys"):
        net.predict.set_keys(mode_logits="x")
    with pytest.raises(ValueError, match="no key named"):
        net.predict.set_keys(fusd="x")
    with pytest.raises(ValueError, match="already the key of"):
        net.fuse.set_keys(fused=keys.PREV_FUSED)


@pytest.mark.parametrize("name,alone", CASES, ids=[f"{n}{'-alone' if a else ''}" for n, a in CASES])
def test_the_carry_is_what_the_stages_declare(name, alone, data):
    """``IMMNet.initial_carry`` is the union of the stages' ``carry_spec`` (no key declared twice; the
    track-start counts ``TrackStart``'s); it primes every key the step reads besides the measurement, holds only
    keys the step writes (so each moves on every scan), and has the keys, shapes and dtypes a real
    rollout's carry has; a stage's ``start_carry`` sets only keys it carries."""
    net = _net(name)
    B, M = data.shape[0], net.n_experts
    z = data.unsqueeze(1).expand(-1, M, -1, -1) if alone else data
    step = net.expert_step if alone else net.step
    carry = _leaves(net.initial_carry(B, alone))
    declared = {}
    for stage in step.module:
        spec = _leaves(TensorDict(stage.carry_spec(B, alone), batch_size=[B]))
        twice = set(spec) & set(declared)
        assert not twice, f"{type(stage).__name__} carries {twice}, declared before it"
        declared.update(spec)
    assert set(carry) == set(declared)
    step_in = {unravel_key(k) for k in step.in_keys} - {keys.MEASUREMENT, *net.start.inputs}  # r, the truth: inputs
    unprimed = [k for k in step_in if not any(_owner(leaf, [k]) for leaf in carry)]
    assert not unprimed, f"the step reads {unprimed}, which no stage carries"
    step_out = [unravel_key(k) for k in step.out_keys]
    assert all(_owner(k, step_out) is not None for k in carry)
    with torch.no_grad():
        _, after_one = net.rollout(z[..., :1, :], experts_alone=alone, **_inputs(net, B, 1))
        _, after = net.rollout(z[..., :SCANS, :], experts_alone=alone, **_inputs(net, B, SCANS))
    rolled = _leaves(after)
    for key, value in carry.items():
        assert rolled[key].shape == value.shape and rolled[key].dtype == value.dtype, key
    x = torch.zeros(z.shape[:-2] + (9,))
    for stage in step.module:
        own = set(_leaves(TensorDict(stage.carry_spec(B, alone), batch_size=[B])))
        for second, before in ((False, net.initial_carry(B, alone)), (True, after_one)):
            before = before.clone(False)
            for key, value in _scan_inputs_at(net, B, 1).items():  # what a start reads beside the carry
                before.set(key, value)
            started = _leaves(TensorDict(stage.start_carry(before, z[..., 1, :], x, second), batch_size=[B]))
            assert set(started) <= own, (type(stage).__name__, set(started) - own)


def _stage_classes():
    import immnet.stages as stages_pkg
    from immnet.stages import classify, correct, filtering, fuse, gain, predict, start, update  # noqa: F401
    from immnet.stages.base import Stage

    seen, todo = set(), [Stage]
    while todo:
        for sub in todo.pop().__subclasses__():
            if sub not in seen and sub.__module__.startswith(stages_pkg.__name__):
                seen.add(sub)
                todo.append(sub)
    return sorted(seen, key=lambda c: c.__qualname__)


@pytest.mark.parametrize("cls", _stage_classes(), ids=lambda c: c.__qualname__)
def test_what_a_stage_declares_it_takes_is_what_its_constructor_takes(cls):
    """IMMNet hands its settings (SET_ONCE) to a component by the class's ``shared`` and ``load_network`` sets a
    gain's weightless options by its ``load_options``, never by reading the constructor: each declaration must name
    exactly the constructor's parameters among those settings, or a setting would be dropped or refused silently."""
    import inspect

    from immnet.stages.network import SET_ONCE

    from immnet.stages import Gain
    from immnet.tracking.networks import _NEEDS_FILTERS

    params = set(inspect.signature(cls).parameters)
    if "options" in params:  # the filter experts' gains: their options are _FilterExperts._init_filter's
        params |= set(inspect.signature(cls._init_filter).parameters)
    assert set(cls.shared) == params & set(SET_ONCE)
    if issubclass(cls, Gain):
        assert set(cls.load_options) == params & set(_NEEDS_FILTERS)
    else:
        assert cls.load_options == ()


@pytest.mark.parametrize("settings", [{"p_stay": 0.9}, {"guard": True}, {"p_stay": 0.9, "guard": {"speeds": False}}])
def test_a_setting_no_component_takes_is_refused_in_one_line(settings):
    """IMMNet's p_stay and guard reach only the components whose ``shared`` names them: on a network of KalmanNet
    gain experts and the Transformer classifier (neither takes them) a value would change nothing, so it is refused;
    ``guard=False`` (no guard) is what that network has, and the same p_stay is taken by the Bayesian update."""
    kalmannet = {"gain": {"class_path": "immnet.stages.KalmanNetGain"},
                 "classifier": {"class_path": "immnet.stages.TransformerClassifier"}}
    with pytest.raises(ValueError, match=" ".join(n for n in ("p_stay", "and", "guard")
                                                  if n in settings or (n == "and" and len(settings) == 2))):
        IMMNet(**kalmannet, **settings)
    IMMNet(**kalmannet, guard=False)
    bayes = IMMNet(gain=kalmannet["gain"], classifier={"class_path": "immnet.stages.BayesTransformerClassifier"},
                   p_stay=0.9)
    assert bayes.classify.p_stay == 0.9


def test_a_checkpoint_written_with_a_setting_no_component_takes_still_loads(tmp_path):
    """A checkpoint saved before IMMNet refused such a setting holds it in its net config: read as a checkpoint
    (``net_arguments(saved=True)``) it is dropped, as that IMMNet dropped it, and the network is the same."""
    from immnet.stages.network import net_arguments

    config = {"gain": {"class_path": "immnet.stages.KalmanNetGain"},
              "classifier": {"class_path": "immnet.stages.TransformerClassifier"}, "p_stay": 0.999, "guard": True}
    assert net_arguments(config, saved=True) == {k: config[k] for k in ("gain", "classifier")}
    with pytest.raises(ValueError, match="p_stay and guard would change nothing"):
        IMMNet(**net_arguments(config))
    kept = dict(config, gain={"class_path": "immnet.stages.filtering.FilterGain"})
    assert net_arguments(kept, saved=True) == kept  # filter experts take both
