"""The output correction (``immnet.stages.correct``, docs/immnet.md "The output correction"): a GRU after the step's
fusion that corrects the position it reports. Held to an independent computation, ``scripts/learned_residual.py``'s
``torch.nn.GRU`` over whole sequences of the model-based filter's own fast path; untrained it is its filter; it
reads nothing after a scan; it starts with each track; it trains through ``immnet fit`` and loads and evaluates
from its checkpoint."""

import json
import runpy

import pytest
import torch

from immnet import keys
from immnet.cli import main
from immnet.config import REPO_ROOT, instantiate, load_yaml
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.data.storage import as_batch, write_dataset
from immnet.filters.methods import method_config
from immnet.imm.measurement import Estimated
from immnet.stages import IMMNet
from immnet.tracking.networks import frame_origin, to_local, to_world
from immnet.tracking.tracker import Tracker, load_network

SCRIPT = REPO_ROOT / "scripts" / "learned_residual.py"
CORRECTION = {"class_path": "immnet.stages.correct.OutputCorrection", "init_args": {"hidden": 16}}


@pytest.fixture(scope="module")
def residual():
    return runpy.run_path(str(SCRIPT))


def _filter(name="real-imm-singer"):
    config = load_yaml(method_config(name))
    config.setdefault("init_args", {})["return_cov"] = True
    return instantiate(config)


def _batch(jitter: bool = False, n: int = 6, T: int = 40):
    """3D-LAST tracks (r 1-7 m) at 1 s scans, or at irregular U[4.5, 5.5] s scans (``t``); missed detections."""
    spec = DataSpec(T=T, min_segment=8, dt=5.0, dt_jitter=0.5) if jitter else DataSpec(T=T, min_segment=8)
    batch = as_batch(generate(n, seed=4, spec=spec))
    z = batch[keys.MEASUREMENTS].double()  # float64, and so the intervals the step is given (intervals_for)
    z[1, 10:13] = float("nan")
    z[3, 25] = float("nan")
    batch[keys.MEASUREMENTS] = z
    return batch


def _corrected_net(method, model, dtype=torch.float64):
    """``method``'s own configuration of the step (``network()``) with the output correction of ``model``'s weights."""
    net = IMMNet(**method.network().config, correction=CORRECTION)
    net.correct.load_state_dict(model.state_dict())
    return net.to(dtype).eval()


def _rollout(net, batch, dtype=torch.float64):
    with torch.no_grad():
        out, _ = net.rollout(batch[keys.MEASUREMENTS].to(dtype), intervals=net.intervals_for(batch),
                             r=batch[keys.R].to(dtype))
    return out


@pytest.mark.parametrize("jitter", [False, True], ids=["1s", "4.5-5.5s"])
def test_the_step_is_the_gru_over_the_filters_fast_path(residual, jitter):
    """The step (IMMNet's stages, scan by scan, the GRU a scan at a time) equals ``torch.nn.GRU`` over the whole
    sequence of features from the filter's own fast path (``PerAxisIMMTracker.track``), in float64: the estimates to
    1e-9 of the state's scale, the corrections to 1e-6 m."""
    batch = _batch(jitter)
    method = _filter("real-imm-singer-5s" if jitter else "real-imm-singer")
    torch.manual_seed(0)
    model = residual["Residual"](30, hidden=16).double()
    torch.nn.init.normal_(model.out.weight, std=0.3)  # a correction of a few metres
    part = residual["prepared"](method, batch)
    expected = residual["predict"](model, part)
    assert (expected - part["state"]).abs().max() > 0.5
    net = _corrected_net(method, model)
    out = _rollout(net, batch)[keys.STATE]
    scale = float(expected.abs().max())  # the filter's two paths agree to 1e-9 of the state's scale (docs/core.md)
    torch.testing.assert_close(out, expected, rtol=0, atol=1e-9 * scale)
    # and the corrections themselves (about a metre) to 1e-6 m: what the filter's paths differ by, carried through
    net.knock_out("correction")
    torch.testing.assert_close(out - _rollout(net, batch)[keys.STATE], expected - part["state"], rtol=0, atol=1e-6)


def test_untrained_it_is_its_filter_and_knocked_out_too():
    """... and its reported covariance is the filter's whatever it corrects (``rollout(return_cov=True)``)."""
    method = _filter()
    batch = _batch()
    base = _rollout(method.network(), batch)
    net = IMMNet(**method.network().config, correction=CORRECTION).double().eval()
    torch.testing.assert_close(_rollout(net, batch)[keys.STATE], base[keys.STATE], rtol=0, atol=0)
    z, r = batch[keys.MEASUREMENTS], batch[keys.R].double()
    with torch.no_grad():
        cov = method.network().rollout(z, r=r, return_cov=True)[0][keys.STATE_COV]
        torch.nn.init.normal_(net.correct.out.weight)
        torch.testing.assert_close(net.rollout(z, r=r, return_cov=True)[0][keys.STATE_COV], cov, rtol=0, atol=0)
    torch.nn.init.normal_(net.correct.out.weight)
    assert (_rollout(net, batch)[keys.STATE] - base[keys.STATE]).abs().max() > 0.5
    net.knock_out("correction")
    torch.testing.assert_close(_rollout(net, batch)[keys.STATE], base[keys.STATE], rtol=0, atol=0)
    with pytest.raises(ValueError, match="no output correction"):
        method.network().knock_out("correction")


def test_it_reads_nothing_after_a_scan_and_starts_with_each_track():
    method = _filter()
    batch = _batch()
    torch.manual_seed(1)
    net = IMMNet(**method.network().config, correction=CORRECTION).double().eval()
    torch.nn.init.normal_(net.correct.out.weight)
    out = _rollout(net, batch)[keys.STATE]
    t = 17
    later = batch.clone()
    z = later[keys.MEASUREMENTS].clone()
    z[:, t + 1 :] += 30.0 * torch.randn_like(z[:, t + 1 :])
    later[keys.MEASUREMENTS] = z
    moved = _rollout(net, later)[keys.STATE]
    torch.testing.assert_close(moved[:, : t + 1], out[:, : t + 1], rtol=0, atol=0)
    assert (moved[:, t + 1 :] - out[:, t + 1 :]).abs().max() > 1.0
    # a track whose first scans are missed is the same track cut to begin at its first detection
    late = batch.clone()
    z = late[keys.MEASUREMENTS].clone()
    z[0, :5] = float("nan")
    late[keys.MEASUREMENTS] = z
    cut = batch[:1].clone()
    cut[keys.MEASUREMENTS] = batch[keys.MEASUREMENTS][:1, 5:]
    cut[keys.STATES] = batch[keys.STATES][:1, 5:]
    torch.testing.assert_close(_rollout(net, late)[keys.STATE][0, 5:], _rollout(net, cut)[keys.STATE][0],
                               rtol=0, atol=1e-9)


def test_the_streaming_tracker_reports_the_corrected_estimate():
    method = _filter()
    batch = _batch()
    torch.manual_seed(2)
    net = IMMNet(**method.network().config, correction=CORRECTION).eval()
    torch.nn.init.normal_(net.correct.out.weight)
    origin = frame_origin(net, batch[keys.MEASUREMENTS])  # the streaming tracker's frame: each track's first detection
    local = batch.clone()
    local.set(keys.MEASUREMENTS, to_local(batch[keys.MEASUREMENTS], origin))
    expected = to_world(_rollout(net, local, torch.float32)[keys.STATE], origin)
    tracker = Tracker(net)
    z, r = batch[keys.MEASUREMENTS].float(), batch[keys.R].float()
    states = torch.stack([tracker.step(z[:, t], r=r)[keys.FUSED] for t in range(z.shape[1])], 1)
    torch.testing.assert_close(states, expected, rtol=0, atol=1e-4)


def test_it_is_refused_where_it_cannot_be():
    with pytest.raises(ValueError, match="fused covariance"):
        IMMNet(correction=CORRECTION)  # the paper's KalmanNet experts carry no covariance


def test_on_filters_that_estimate_r_it_reads_their_estimate():
    """With the filters' r estimated from each track's measurements (``FilterGain(r=None)``, as IMMNet's real-flight
    networks), the correction scales by that estimate and the step needs no ``r``: the same tracks measured with
    twice the noise are corrected by about twice as much where its input is the same."""
    config = dict(_filter().network().config)
    config["gain"] = {**config["gain"], "init_args": {**config["gain"]["init_args"], "r": None}}
    net = IMMNet(**config, correction=CORRECTION).double().eval()
    assert keys.NOISE_VAR in net.correct.in_keys and keys.R not in net.step.in_keys
    with torch.no_grad():
        net.correct.out.bias.copy_(torch.tensor([1.0, 0.0, 0.0]))  # delta = (1, 0, 0) in units of r, whatever it reads
    batch = _batch()
    z = batch[keys.MEASUREMENTS]
    with torch.no_grad():
        out, _ = net.rollout(z)
        base, carry = net.knock_out("correction").rollout(z)
    r_est = carry.get(keys.NOISE_VAR).sqrt()
    torch.testing.assert_close(out[keys.STATE][:, -1, 0] - base[keys.STATE][:, -1, 0], r_est, rtol=1e-9, atol=0)
    assert ((r_est - batch[keys.R].double()).abs() / batch[keys.R].double()).max() < 0.5  # an estimate of r


@pytest.mark.slow
def test_the_recipe_trains_loads_and_evaluates(tmp_path, monkeypatch):
    """``recipes/real-singer-output.yaml`` (the shipped ``real``'s) at tiny size through ``immnet fit``: only the
    correction learns (the filters are the tuned filter's buffers, each track's r estimated), its checkpoint rebuilds
    the network with the correction, and ``immnet evaluate`` scores it told r as the filter is (barely trained, it
    is about that filter)."""
    from tests.tiny_runs import TINY

    monkeypatch.chdir(tmp_path)
    data = tmp_path / "runs/real/data/quickstart-1s"
    write_dataset(data / "train", 12, seed=3, spec=TINY)
    write_dataset(data / "val", 6, seed=4, spec=TINY)
    main(["fit", "--config", str(REPO_ROOT / "recipes/real-singer-output.yaml"), "--trainer.max_steps", "3",
          "--trainer.val_check_interval", "3", "--data.batch_size", "4", "--trainer.logger", "false"])
    ckpt = tmp_path / "runs/real/output/checkpoints/best.ckpt"
    net = load_network(ckpt)
    assert net.correct is not None and float(net.correct.out.weight.abs().max()) > 0
    assert all(name.startswith("correct.") for name, _ in net.named_parameters())  # the filters learn nothing
    assert isinstance(net.gain.measurement, Estimated)  # each track's r estimated
    config = _filter().network().config
    config["gain"] = {**config["gain"], "init_args": {**config["gain"]["init_args"], "r": None}}
    base = IMMNet(**config)
    for name, value in base.state_dict().items():  # and are the tuned filter's
        torch.testing.assert_close(net.state_dict()[name].double(), value.double(), rtol=1e-6, atol=0)
    out = tmp_path / "res.json"
    assert main(["evaluate", "--data", str(data / "val"), "--split", "all", "--methods", "real-imm-singer,immnet",
                 "--checkpoint", f"immnet={ckpt}", "--told-r", "--json", str(out), "--quiet"]) == 0
    res = json.loads(out.read_text())["methods"]
    assert res["immnet"]["rmse"]["avg"] == pytest.approx(res["real-imm-singer"]["rmse"]["avg"], rel=0.05)


def _general_with_correction(**module_args):
    """The shipped general network with an output correction added, as
    ``recipes/general-output.yaml`` builds it."""
    from immnet.checkpoints import shipped
    from immnet.training import Stage2Module

    path = shipped("general")
    net = dict(load_network(path).config, correction=CORRECTION)
    return path, Stage2Module(net=net, init_checkpoint=str(path), **module_args)


def test_a_correction_added_to_a_trained_network_starts_as_that_network():
    path, module = _general_with_correction()
    batch = as_batch(generate(4, seed=5, spec=DataSpec(T=40, min_segment=10)))
    z = batch[keys.MEASUREMENTS].float()
    with torch.no_grad():
        shipped_out, _ = load_network(path).eval().rollout(z)
        out, _ = module.net.eval().rollout(z)
    assert module.net.correct is not None
    torch.testing.assert_close(out[keys.STATE], shipped_out[keys.STATE], rtol=0, atol=0)


def test_learn_trains_the_named_components_alone():
    """``Stage2Module(learn=["correction"])``: one optimizer step moves the correction's weights and leaves every
    other weight of the trained network bit for bit."""
    _, module = _general_with_correction(learn=["correction"], gamma=1.0, tbptt=0)
    learn = {n for n, p in module.named_parameters() if p.requires_grad}
    assert learn and all(n.startswith("net.correct.") for n in learn)
    assert {id(p) for p in module.trainable_parameters()} == {id(p) for p in module.net.correct.parameters()}
    opt = torch.optim.Adam(module.trainable_parameters(), 1e-3)
    module.optimizers = lambda: opt  # the module's own loop without a Trainer (as benchmarks/bench_immnet.py)
    module.manual_backward = lambda loss: loss.backward()
    module.log = lambda *a, **k: None
    module.net.correct.out.weight.data.normal_(0, 0.01)  # a correction that has started to learn: gradients flow
    before = {n: v.clone() for n, v in module.state_dict().items()}
    batch = as_batch(generate(4, seed=6, spec=DataSpec(T=30, min_segment=8)), torch.float32)
    module.train()
    module.training_step(batch, 0)
    after = module.state_dict()
    moved = {n for n in before if not torch.equal(before[n], after[n])}
    assert moved and all(n.startswith("net.correct.") for n in moved), sorted(moved)[:5]


@pytest.mark.parametrize("learn, message", [(["mixer"], "unknown component"), ([], "unknown component"),
                                            (["correction"], "has no parameters")])
def test_learn_refuses_what_the_network_cannot_learn(learn, message):
    from immnet.training import Stage2Module

    net = _filter().network().config  # real-imm-singer: filters alone, no correction
    with pytest.raises(ValueError, match=message):
        Stage2Module(net=net, learn=learn)


def test_learned_parts_rows_are_the_parts_the_network_has():
    """``IMMNet.learned_parts`` and ``scripts/learned_parts.py`` knock out only what a network learned: the shipped
    real network's output correction alone, the 3D-LAST network's KalmanNet and Transformer and both, nothing of a
    model-based filter; the names are those ``Stage2Module(learn=...)`` and ``IMMNet.knock_out`` take."""
    from immnet.checkpoints import shipped

    variants = runpy.run_path(str(REPO_ROOT / "scripts" / "learned_parts.py"))["variants"]
    assert load_network(shipped("real")).learned_parts() == ["correction"]
    assert list(variants(["correction"]).values()) == [(), ("correction",)]
    assert load_network(shipped("3dlast")).learned_parts() == ["gain", "classifier"]
    assert list(variants(["gain", "classifier"]).values()) == [(), ("gain",), ("classifier",), ("gain", "classifier")]
    assert _filter().network().learned_parts() == [] and list(variants([]).values()) == [()]
    with pytest.raises(ValueError, match="no learned part 'output'; parts: gain, classifier, correction"):
        _filter().network().part("output")


def test_the_correction_features_have_finite_gradients_where_a_variance_is_zero():
    """A track before its first detection carries a zero covariance and its features are not used: their gradient (0)
    must not turn into NaN through sqrt's infinite derivative at 0 (it did, and a training whose batch held such a
    track skipped that step). A zero variance in a used feature (a CV filter's acceleration) gets a zero gradient too.
    The features' values stay the square roots of the variances (float64 numpy)."""
    import numpy as np

    from immnet.stages.correct import cholesky_noise, correction_features, whitened_features

    torch.manual_seed(0)
    B = 3
    z = torch.randn(B, 3, dtype=torch.float64) * 10
    z[0] = float("nan")  # no detection yet
    x = torch.randn(B, 9, dtype=torch.float64, requires_grad=True)
    A = torch.randn(B, 9, 9, dtype=torch.float64)
    P0 = A @ A.transpose(-1, -2)
    P0[0] = 0.0  # a track that has not started
    P0[1, 2, :] = 0.0
    P0[1, :, 2] = 0.0  # x's acceleration variance zero
    P = P0.clone().requires_grad_(True)
    mu = torch.full((B, 4), 0.25, dtype=torch.float64)
    r = torch.full((B, 1), 5.0, dtype=torch.float64)
    L = cholesky_noise(25.0 * torch.eye(3, dtype=torch.float64).expand(B, 3, 3))
    for f in (correction_features(z, x, P, mu, r, 1.0), whitened_features(z, x, P, mu, L, 1.0)):
        x.grad = P.grad = None
        f[1:].sum().backward()  # the track that has not started: its features unused
        assert torch.isfinite(x.grad).all() and torch.isfinite(P.grad).all()
        assert P.grad[1, 2, 2] == 0.0
        var = np.diagonal(P0.numpy(), axis1=-2, axis2=-1)
        np.testing.assert_allclose(f[:, 13:16].detach().numpy(), np.sqrt(var[:, [1, 4, 7]]), rtol=1e-12)
        np.testing.assert_allclose(f[:, 16:19].detach().numpy(), np.sqrt(var[:, [2, 5, 8]]), rtol=1e-12)


def test_the_heading_frame_has_a_finite_gradient_at_rest():
    """A track at rest (a one-point start's zero velocity) has heading 0 (cos 1, sin 0) and a zero gradient there,
    not sqrt's 0 * inf = NaN; elsewhere the heading is atan2's (float64)."""
    import math

    from immnet.stages.classify import heading_frame

    v = torch.tensor([[0.0, 0.0, 3.0], [3.0, -4.0, 0.0], [-1.0, 2.0, 5.0]], dtype=torch.float64, requires_grad=True)
    c, s = heading_frame(v)
    (c + s).sum().backward()
    assert torch.isfinite(v.grad).all() and (v.grad[0] == 0).all()
    for k in (1, 2):
        h = math.atan2(v[k, 1].item(), v[k, 0].item())
        assert abs(c[k].item() - math.cos(h)) < 1e-12 and abs(s[k].item() - math.sin(h)) < 1e-12
    assert (c[0].item(), s[0].item()) == (1.0, 0.0)
