"""Method classes: configs build, outputs have the protocol's shapes, bad inputs fail clearly."""

from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from immnet import keys
from immnet.config import REPO_ROOT, build
from immnet.filters import ClairvoyantKF, IMMTracker, KalmanFilterTracker, data_mode_probs
from immnet.motion import ConstantVelocity, ModelSet, MotionModel
from tiny_runs import at_an_interval_it_takes

METHOD_CONFIGS = sorted((REPO_ROOT / "configs" / "methods").glob("*.yaml"))


def _batch(B=4, T=30, seed=0):
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T, dtype=torch.float64)
    pos = torch.stack([1e4 + 100 * t, -5e3 + 50 * t, 3e3 + 0 * t], -1).expand(B, T, 3)
    z = pos + 3 * torch.randn(B, T, 3, generator=g, dtype=torch.float64)
    states = torch.zeros(B, T, 9, dtype=torch.float64)
    states[..., 0::3], states[..., 1] , states[..., 4] = pos, 100.0, 50.0
    return TensorDict(
        {"measurements": z, "states": states, "mode": torch.zeros(B, T, dtype=torch.long),
         "turn_rate": torch.zeros(B, T, dtype=torch.float64), "r": torch.full((B,), 3.0, dtype=torch.float64),
         "dt": torch.ones(B, dtype=torch.float64)},
        batch_size=[B],
    )


@pytest.mark.parametrize("path", METHOD_CONFIGS, ids=[p.stem for p in METHOD_CONFIGS])
def test_method_config_builds_and_tracks(path: Path):
    method = build(path)
    assert method.name == path.stem and isinstance(method.needs, tuple)
    out = method.track(at_an_interval_it_takes(method, _batch()))
    assert out.batch_size == torch.Size([4]) and out["state"].shape == (4, 30, 9)
    assert torch.isfinite(out["state"]).all()
    torch.testing.assert_close(out["state"][:, 0, 0::3], _batch()["measurements"][:, 0])  # t = 0: first measurement
    if "mode_probs" in out.keys():
        assert out["mode_probs"].shape == (4, 30, 4)
        torch.testing.assert_close(out["mode_probs"].sum(-1), torch.ones(4, 30, dtype=torch.float64))


def test_mode_probs_summed_per_data_mode():
    imm = IMMTracker("configs/model_sets/imm6.yaml", 3.0, 0.5, return_experts=True)
    out = imm.track(_batch())
    probs = out["mode", "probs"]
    assert probs.shape == (4, 30, 6) and out["expert", "post"].shape == (4, 30, 6, 9)
    mp = out["mode_probs"]
    torch.testing.assert_close(mp[..., 2], probs[..., 2] + probs[..., 3])
    torch.testing.assert_close(mp[..., 3], probs[..., 4] + probs[..., 5])
    assert (data_mode_probs(torch.ones(2, 1), torch.tensor([1]))[:, [0, 2, 3]] == 0).all()


def test_non_uniform_dt_and_float32():
    batch = _batch()
    batch["dt"] = torch.tensor([1.0, 1.0, 0.5, 2.0], dtype=torch.float64)
    out64 = IMMTracker("configs/model_sets/imm3.yaml", 3.0, 0.5).track(batch)
    out32 = IMMTracker("configs/model_sets/imm3.yaml", 3.0, 0.5, dtype="float32").track(batch)
    assert out32["state"].dtype == torch.float32
    assert (out32["state"][..., 0::3].double() - out64["state"][..., 0::3]).abs().max() < 0.05
    kf = KalmanFilterTracker(ConstantVelocity(), 3.0, 0.5).track(batch)
    assert torch.isfinite(kf["state"]).all()


def test_missed_detections_keep_estimates_finite():
    batch = _batch()
    batch["measurements"][0, 0] = float("nan")  # first scan missed: no estimate until the first detection
    batch["measurements"][1, 10:15] = float("nan")
    batch["measurements"][2, 7, 1] = float("nan")
    for method in (IMMTracker("configs/model_sets/imm4.yaml", 3.0, 0.5), ClairvoyantKF()):
        state = method.track(batch)["state"]
        assert torch.isnan(state[0, 0]).all()
        assert torch.isfinite(state[0, 1:]).all() and torch.isfinite(state[1:]).all()


class _Wide(MotionModel):
    name = "wide"

    def F(self, dt=1.0, dtype=torch.float64, device=None):
        return torch.eye(12, dtype=dtype, device=device)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"model_set": ModelSet([ConstantVelocity(), _Wide()])}, "mixes state dimensions"),
        ({"p_stay": [[0.9, 0.2, 0.0], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8]]}, "rows must sum to 1"),
        ({"p_stay": [[1.1, -0.1, 0.0], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8]]}, "non-negative"),
        ({"p_stay": [[0.5, 0.5], [0.5, 0.5]]}, "must be 3x3"),
        ({"p_stay": 1.5}, "p_stay"),
        ({"sigma_q": -0.1}, "sigma_q"),
        ({"sigma_q": [0.1, 0.2]}, "sigma_q has 2 values"),
        ({"r": 0.0}, "r must be"),
        ({"mu0": [0.5, 0.5]}, "one probability per model"),
        ({"mu0": [0.5, 0.4, 0.3]}, "sum to 1"),
        ({"dtype": "float16"}, "dtype"),
        ({"model_set": "configs/model_sets/imm4-adaptive.yaml"}, "state-dependent"),
    ],
    ids=["dims", "rows", "negative", "shape", "p_stay", "neg-sigma", "sigma-len", "r", "mu0-len", "mu0-sum", "dtype", "state-dependent"],
)
def test_imm_rejects_bad_configuration(kwargs, message):
    args = {"model_set": "configs/model_sets/imm3.yaml", "r": 3.0, "sigma_q": 0.5, **kwargs}
    with pytest.raises(ValueError, match=message):
        IMMTracker(**args)


@pytest.mark.parametrize("missing", ["turn_rate", "mode", "r"])
def test_clairvoyant_names_missing_ground_truth(missing):
    batch = _batch().exclude(missing)
    with pytest.raises(ValueError, match=f"clairvoyant needs '{missing}' \\(ground truth\\), which this data lacks"):
        ClairvoyantKF().track(batch)


@pytest.mark.slow
def test_compiled_imm_tracker_equals_eager():
    """``IMMTracker(compile=True)`` takes the compiled fused step and gives the eager IMM's numbers."""
    batch = _batch()
    args = {"model_set": "configs/model_sets/imm3.yaml", "r": 4.0, "sigma_q": 0.5}
    eager, compiled = IMMTracker(**args).track(batch), IMMTracker(**args, compile=True).track(batch)
    torch.testing.assert_close(compiled[keys.STATE], eager[keys.STATE], rtol=1e-9, atol=1e-7)
    torch.testing.assert_close(compiled[keys.MODE_PROBS], eager[keys.MODE_PROBS], rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("compile_step", [False, True])
def test_a_mode_that_nothing_enters_keeps_the_track_finite(compile_step):
    """``p_stay`` 1 (accepted: a bank of filters that never switch) once a mode's probability underflows to 0: its
    mixing weights were ``0 / 0`` and the NaN reached every filter and the track. They are 0 now, in the core's loop
    and in the fused step (run eagerly here), and the mode keeps probability 0."""
    from immnet.data.generate import generate
    from immnet.filters.imm import initial_state
    from immnet.filters.imm_fused import fused_step, imm_filter_fused

    data = generate(2, seed=1)
    models = [{"class_path": "immnet.motion.ConstantVelocity"}, {"class_path": "immnet.motion.ConstantAcceleration"}]
    imm = IMMTracker(models, r=3.0, sigma_q=[0.01, 1.0], p_stay=1.0)
    if compile_step:
        z = data["measurements"]
        x0, P0 = initial_state(z, 3.0)
        F, Q, Pi, mu0 = imm.matrices(1.0)
        state, probs, _ = imm_filter_fused(z, x0, P0, F, Q, torch.tensor(9.0, dtype=z.dtype), Pi, mu0, False,
                                           step=fused_step)
    else:
        out = imm.track(data)
        state, probs = out["state"], out["mode_probs"][..., :2]
    assert torch.isfinite(state).all() and torch.isfinite(probs).all()
    assert (probs == 0).any()  # a mode did underflow
