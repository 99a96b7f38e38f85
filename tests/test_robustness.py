"""Out of distribution: the turn-rate-estimating trackers follow turns faster than 3D-LAST's (docs/robustness.md)."""

import pytest
import torch

from immnet import keys
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.filters.methods import build_method
from immnet.evaluation.metrics import per_trajectory_rmse, position_error

TRACKERS = ["imm-ekf", "imm-ekf-guard", "imm-ekf-guard-sticky", "immnet"]
MODEL_BASED = ["imm-ekf", "imm-ekf-guard", "imm-ekf-guard-sticky"]


@pytest.fixture(scope="module")
def fast_turns():
    """20 trajectories whose turns fly at 10-15 deg/s (3D-LAST's: 1-10), as configs/data/ood/turns.yaml."""
    data = generate(20, seed=2020, spec=DataSpec(T=150, min_segment=50, turn_rate_min_deg=10.0, turn_rate_max_deg=15.0))
    per_track = {}
    with torch.no_grad():
        for name in ["measurements", *TRACKERS]:
            state = build_method(name).track(data)[keys.STATE]
            per_track[name] = per_trajectory_rmse(position_error(state, data[keys.STATES])).mean(-1)
    return per_track


@pytest.mark.parametrize("name", TRACKERS)
def test_no_track_diverges_on_turns_faster_than_the_prior(fast_turns, name):
    """Issue 20, item 7: on 10-15 deg/s turns no track of the turn-rate-estimating trackers diverges (a track's
    RMSE beyond 3x the raw measurements' on that track); with the turn rate bounded at the prior's 10 deg/s
    the turn filters fell behind (imm-ekf 10.5 m against the measurements' 4.0 m)."""
    ratio = fast_turns[name] / fast_turns["measurements"]
    assert float(ratio.max()) < 3.0, f"{name}: a track at {float(ratio.max()):.1f}x the raw measurements"


def test_immnet_below_raw_and_near_the_best_imm_on_fast_turns(fast_turns):
    """Issue 20, item 7: IMMNet beats the raw measurements on 10-15 deg/s turns and stays within 1.5x the best
    model-based IMM (it was above raw, 4.3 m against 4.0 m, its turn experts bounded at 10 deg/s)."""
    avg = {k: float(v.mean()) for k, v in fast_turns.items()}
    assert avg["immnet"] < avg["measurements"]
    assert avg["immnet"] <= 1.5 * min(avg[m] for m in MODEL_BASED)
