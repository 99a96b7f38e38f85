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
