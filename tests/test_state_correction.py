"""KalmanNet's learned state correction (``KalmanNetFilterGain(state_correction=...)``, docs/notebook/real-flights.md "A
learned state correction"): the update adds it to each expert's posterior mean and leaves the covariance the filter's;
knocked out, the network is exactly the one without it; bad settings are refused by name."""

import pytest
import torch
from tensordict import TensorDict

from immnet import keys
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.motion import ConstantAcceleration, ConstantVelocity, ModelSet
from immnet.stages import IMMNet
from immnet.stages.filtering import FilterUpdate

FILTERING = "immnet.stages.filtering."
MODELS = [{"class_path": "immnet.motion.ConstantVelocity"}, {"class_path": "immnet.motion.ConstantAcceleration"}]


def _config(correction):
    init = {"interaction": "imm", "onset": False, "model_noise": [0.4, 0.35], "start_acc_std": 10.0}
    if correction is not None:
        init["state_correction"] = correction
    return {"model_set": MODELS, "p_stay": 0.98, "modes": "axis", "guard": False,
            "gain": {"class_path": FILTERING + "KalmanNetFilterGain", "init_args": init},
            "classifier": {"class_path": "immnet.stages.BayesTransformerClassifier"}}


@pytest.fixture(scope="module")
def z():
    td = generate(5, seed=4, spec=DataSpec(T=40, min_segment=10))
    z = td[keys.MEASUREMENTS].double()
    z[1, 7] = z[3, 20:23] = float("nan")  # missed detections
    return z


def test_the_update_adds_the_correction_to_the_mean_and_keeps_the_covariance():
    """``x+ = x- + K (z - H x-) + c``, computed by hand; the covariance equals the update's without the correction."""
    g = torch.Generator().manual_seed(0)
    B, M = 4, 2
    P = torch.randn(B, M, 10, 10, generator=g, dtype=torch.float64)
    td = TensorDict({
        keys.MEASUREMENT: torch.randn(B, 3, generator=g, dtype=torch.float64) * 10,
        keys.EXPERT_PRIOR: torch.randn(B, M, 9, generator=g, dtype=torch.float64) * 10,
        keys.EXPERT_GAIN: torch.rand(B, M, 9, 3, generator=g, dtype=torch.float64),
        keys.EXPERT_RATE: torch.zeros(B, M, dtype=torch.float64),
        keys.EXPERT_RATE_GAIN: torch.zeros(B, M, 3, dtype=torch.float64),
        keys.EXPERT_AUG_PRIOR_COV: P @ P.transpose(-1, -2) + torch.eye(10, dtype=torch.float64),
        keys.NOISE_VAR: torch.full((B,), 4.0, dtype=torch.float64),
        keys.EXPERT_CORRECTION: torch.randn(B, M, 9, generator=g, dtype=torch.float64),
    }, batch_size=[B])
    td.get(keys.MEASUREMENT)[2] = float("nan")  # a missed detection: the prior plus the correction
    ms = ModelSet([ConstantVelocity(), ConstantAcceleration()])
    with_c = FilterUpdate(ms, correction=True)(td.clone())
    without = FilterUpdate(ms)(td.exclude(keys.EXPERT_CORRECTION).clone())
    prior, K, c = td.get(keys.EXPERT_PRIOR), td.get(keys.EXPERT_GAIN), td.get(keys.EXPERT_CORRECTION)
    nu = torch.nan_to_num(td.get(keys.MEASUREMENT)[:, None, :] - prior[..., [0, 3, 6]], nan=0.0)
    expected = prior + torch.einsum("bmij,bmj->bmi", K, nu) + c
    torch.testing.assert_close(with_c.get(keys.EXPERT_POST), expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(with_c.get(keys.EXPERT_POST)[2], prior[2] + c[2], rtol=0, atol=1e-12)
    assert torch.equal(with_c.get(keys.EXPERT_AUG_COV), without.get(keys.EXPERT_AUG_COV))
    assert keys.EXPERT_CORRECTION in FilterUpdate(ms, correction=True).in_keys
    assert keys.EXPERT_CORRECTION not in FilterUpdate(ms).in_keys


def test_knocked_out_the_network_is_the_one_without_it(z):
    """The correction's rows of FC2 zeroed, the network tracks exactly as one without a correction whose other
    weights are the same: the correction is the only thing it adds. With the rows as initialised, its estimates
    move, each expert's correction within its bounds."""
    torch.manual_seed(0)
    net = IMMNet(**_config([2.0, 1.0, 0.5])).double().eval()
    plain = IMMNet(**_config(None)).double().eval()
    state = net.state_dict()
    rows = {k: v[:, : -net.gain.n_correction] for k, v in state.items() if k.startswith("gain.fc2b.")}
    plain.load_state_dict(state | rows)
    with torch.no_grad():
        base, _ = plain.rollout(z)
        trained, _ = net.rollout(z)
        assert (trained[keys.STATE] - base[keys.STATE]).abs().max() > 1e-6  # the correction moves the estimates
        td = net.initial_carry(z.shape[0], dtype=torch.float64)
        for t in range(5):
            td = net.scan(td, z[:, t])
        c = td.get(keys.EXPERT_CORRECTION)
        assert c.shape == (z.shape[0], 2, 9) and c.abs().max() > 0
        assert torch.all(c.abs() <= net.gain.correction_scale.to(c.dtype))
        net.knock_out("state_correction")
        out, _ = net.rollout(z)
    torch.testing.assert_close(out[keys.STATE], base[keys.STATE], rtol=0, atol=1e-9)
    torch.testing.assert_close(out[keys.ROLLOUT_EXPERT_PROBS], base[keys.ROLLOUT_EXPERT_PROBS], rtol=0, atol=1e-12)


def test_bad_settings_are_refused_by_name():
    with pytest.raises(ValueError, match="state_correction needs three bounds > 0"):
        IMMNet(**_config([2.0, 0.0, 0.5]))
    with pytest.raises(ValueError, match="state_correction needs three bounds > 0"):
        IMMNet(**_config([2.0, 1.0]))
    with pytest.raises(ValueError, match="has no state correction"):
        IMMNet(**_config(None)).knock_out("state_correction")
    with pytest.raises(ValueError, match="no learned part 'noise'"):
        IMMNet(**_config(None)).knock_out("noise")
