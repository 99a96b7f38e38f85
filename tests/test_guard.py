"""The range guard (``immnet.imm.guard``): its events on geometry worked out by hand, the
transition matrix and rate blend against closed forms, and what it is worth on the generator's data."""

import math

import numpy as np
import pytest
import torch

from immnet import keys
from immnet.data.generate import generate
from immnet.evaluation.metrics import position_error, rmse
from immnet.filters import IMMEKF, transition_matrix
from immnet.imm.guard import G_MAX, RangeGuard, fresh_share, guarded_transition
from immnet.imm.interaction import mix

DEG = math.pi / 180.0
MODES = torch.tensor([0, 1, 2, 3])


def _state(lx, ly, vx, vy):
    x = torch.zeros(9, dtype=torch.float64)
    x[0], x[3], x[1], x[4] = lx, ly, vx, vy
    return x


def _events(x, w=0.0):
    return [float(e) for e in RangeGuard().events(x, torch.tensor(w, dtype=torch.float64), 1.0)]


def test_onset_beyond_the_outer_bound_turns_toward_the_radar():
    # at (34 km, 0) flying out and a little north: turning toward the radar is counter-clockwise (w > 0)
    pos, neg, clear, _ = _events(_state(34_000.0, 0.0, 200.0, 50.0))
    assert pos > 0.99 and neg < 1e-6 and clear < 1e-6
    pos, neg, _, _ = _events(_state(34_000.0, 0.0, 200.0, -50.0))  # a little south: clockwise
    assert neg > 0.99 and pos < 1e-6
    assert max(_events(_state(34_000.0, 0.0, -200.0, 50.0))) < 1e-6  # flying in: no event
    assert max(_events(_state(20_000.0, 0.0, 200.0, 50.0))) < 1e-6  # inside the region: none


def test_onset_within_the_inner_bound_turns_away_from_the_radar():
    # at (3 km, 0) flying in and a little north: turning away is clockwise (w < 0)
    pos, neg, _, _ = _events(_state(3_000.0, 0.0, -150.0, 40.0))
    assert neg > 0.99 and pos < 1e-6
    assert max(_events(_state(3_000.0, 0.0, 150.0, 40.0))) < 1e-6  # flying out: none


def test_a_bound_turn_clears_on_the_scan_its_heading_points_back_30_degrees():
    v, rho = 200.0, 34_000.0

    def at(share):  # the velocity at radial share `share` (outward > 0), turning counter-clockwise
        a = math.asin(share)
        return _state(rho, 0.0, v * math.sin(a), v * math.cos(a))

    # this scan -0.55, the scan before (rotated back by 8 deg/s) about -0.43: the first beyond -1/2
    # (0.9 rather than 1: the ramps are share_soft = 0.02 wide, and -0.55 is 2.5 of them past -1/2)
    assert _events(at(-0.55), 8 * DEG)[2] > 0.85
    assert _events(at(-0.75), 8 * DEG)[2] < 0.01  # already past it a scan ago
    assert _events(at(-0.40), 8 * DEG)[2] < 0.01  # not yet
    assert _events(at(-0.55), 2 * DEG)[2] < 0.05  # a slow turn is not the bound's turn (and had not crossed)


def test_guarded_transition_rows_are_distributions_and_events_go_to_their_modes():
    Pi = transition_matrix(0.99, 4)
    B = 3
    zero = torch.zeros(B, 4, dtype=torch.float64)
    same, share, by_speed = guarded_transition(Pi, (zero, zero, zero, zero), MODES)
    torch.testing.assert_close(same, Pi.expand(B, 4, 4).to(torch.float64))
    assert share.abs().max() == 0 and by_speed.abs().max() == 0
    pos = zero.clone()
    pos[0] = 0.5  # track 0: every filter sees a 50 % onset into CT+
    clear = zero.clone()
    clear[1] = 1.0  # track 1: certain clear of every turn filter (only the turns take it), capped at G_MAX
    out, share, by_speed = guarded_transition(Pi, (pos, zero, clear, zero), MODES)
    torch.testing.assert_close(out.sum(-1), torch.ones(B, 4, dtype=torch.float64))
    expect0 = 0.5 * Pi.to(torch.float64)
    expect0[:, 2] += 0.5
    torch.testing.assert_close(out[0], expect0)
    torch.testing.assert_close(share[0, :, 2], 0.5 / expect0[:, 2])
    assert share[0, :, [0, 1, 3]].abs().max() == 0
    torch.testing.assert_close(out[1, :2], Pi[:2].to(torch.float64))  # CV and CA do not clear
    torch.testing.assert_close(out[1, 2:, 0], (1 - G_MAX) * Pi[2:, 0].to(torch.float64) + G_MAX)


def _ca(vx, vy, ax, ay, vz=0.0, az=0.0):
    x = _state(15_000.0, 0.0, vx, vy)
    x[2], x[5], x[7], x[8] = ax, ay, vz, az
    return x


def test_speed_onset_is_the_first_scan_out_of_the_speed_bounds():
    """A CA leaving [40, 330] m/s (or |vz| 25 m/s) turns for one scan (docs/spec.md section 2): the event is the
    chance that the speed is out now but was in a scan ago (the estimate's own acceleration taking it back),
    with ramps bound_speed_soft = 1 m/s wide: 1 - sigmoid(x) at 1.5 m/s past a bound is 0.18, at 0.5 m/s 0.38."""
    sig = lambda u: 1 / (1 + math.exp(-u))  # noqa: E731
    speed = lambda x: _events(x)[3]  # noqa: E731
    # 331.5 m/s after +2 m/s^2: out now with 1 - sigmoid(-1.5), in a scan ago (329.5) but for sigmoid(-0.5)
    now, before = 1 - sig(-1.5), 1 - sig(0.5)
    assert speed(_ca(0.0, 331.5, 0.0, 2.0)) == pytest.approx((now - before) / (1 - before), rel=1e-6)
    assert speed(_ca(0.0, 331.5, 0.0, 2.0)) > 0.5
    assert speed(_ca(39.0, 0.0, -2.0, 0.0)) > 0.5  # below 40 m/s, decelerating
    assert speed(_ca(150.0, 0.0, 0.0, 0.0, vz=26.0, az=2.0)) > 0.5  # climbing past 25 m/s
    assert speed(_ca(0.0, 340.0, 0.0, 0.0)) < 1e-6  # out a scan ago too: no new event
    assert speed(_ca(0.0, 331.5, 0.0, -2.0)) < 1e-6  # slowing back in
    assert speed(_ca(200.0, 50.0, 3.0, 0.0)) < 1e-6  # well inside
    off = RangeGuard(speeds=False).events(_ca(0.0, 331.5, 0.0, 2.0), torch.tensor(0.0, dtype=torch.float64), 1.0)
    assert float(off[3]) == 0.0


def test_a_speed_onset_leaves_ca_only_for_either_turn_and_a_fresh_speed_turn_clears():
    Pi = transition_matrix(0.99, 4).to(torch.float64)
    zero = torch.zeros(2, 4, dtype=torch.float64)
    speed = torch.full((2, 4), 0.6, dtype=torch.float64)  # every filter's estimate is out of bounds
    fresh = zero.clone()
    fresh[1, 3] = 0.8  # track 1: 80 % of the CT- filter's prior entered at a speed bound on the last scan
    out, share, by_speed = guarded_transition(Pi, (zero, zero, zero, speed), MODES, fresh)
    torch.testing.assert_close(out.sum(-1), torch.ones(2, 4, dtype=torch.float64))
    torch.testing.assert_close(out[0, [0, 2, 3]], Pi[[0, 2, 3]])  # only CA's row turns
    expect = 0.4 * Pi[1].clone()
    expect[2:] += 0.3
    torch.testing.assert_close(out[0, 1], expect)
    torch.testing.assert_close(by_speed[0, 1, 2:], 0.3 / expect[2:])
    torch.testing.assert_close(share[0, 1], by_speed[0, 1])  # the speed turns are bound turns (the bound's rate)
    clear_row = 0.2 * Pi[3].clone()
    clear_row[0] += 0.8
    torch.testing.assert_close(out[1, 3], clear_row)  # to CV
    # carried: the speed-entered share of each filter's mixed prior, sum_i mu_{i|j} speed_ij
    w = torch.softmax(torch.randn(2, 4, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64), 1)
    np.testing.assert_allclose(fresh_share(w, by_speed).numpy(), np.einsum("bij,bij->bj", w.numpy(), by_speed.numpy()))


def test_rate_blend_is_the_moment_matched_two_component_mixture():
    g = torch.Generator().manual_seed(0)
    A = torch.randn(4, 10, 10, generator=g, dtype=torch.float64)
    P = A @ A.transpose(-1, -2) + torch.eye(10, dtype=torch.float64)
    y = torch.randn(4, 10, generator=g, dtype=torch.float64)
    share = torch.tensor([0.0, 0.3, 0.8, 1.0], dtype=torch.float64)
    rate, var = torch.tensor(0.14, dtype=torch.float64), 1e-4
    # one filter entering itself (w = 1), a share of it the bound turn: rate ``N(0.14, var)``
    one = torch.ones(4, 1, 1, dtype=torch.float64)
    y2, P2 = mix(one, y[:, None], P[:, None], bound=(share[:, None, None], rate.reshape(1), var, 9))
    y2, P2 = y2[:, 0], P2[:, 0]
    for b in range(4):
        a = float(share[b])
        m1, C1 = y[b].numpy(), P[b].numpy()
        m2, C2 = m1.copy(), C1.copy()
        m2[9] = 0.14
        C2[9, :] = C2[:, 9] = 0.0
        C2[9, 9] = var
        m = (1 - a) * m1 + a * m2
        C = (1 - a) * (C1 + np.outer(m1 - m, m1 - m)) + a * (C2 + np.outer(m2 - m, m2 - m))
        np.testing.assert_allclose(y2[b].numpy(), m, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(P2[b].numpy(), C, rtol=1e-10, atol=1e-12)


def test_guard_settings_are_checked():
    assert RangeGuard.from_config(None) is None and RangeGuard.from_config(False) is None
    assert RangeGuard.from_config(True) == RangeGuard()
    assert RangeGuard.from_config({"outer": 30_000.0}).outer == 30_000.0
    with pytest.raises(ValueError, match="unknown RangeGuard field"):
        RangeGuard.from_config({"outter": 1.0})
    with pytest.raises(ValueError, match="inner"):
        RangeGuard(inner=40_000.0)
    with pytest.raises(ValueError, match="rate_deg"):
        RangeGuard(rate_deg=-8.0)
    with pytest.raises(ValueError, match="guard must be"):
        RangeGuard.from_config("yes")
    with pytest.raises(ValueError, match="speed_min"):
        RangeGuard(speed_min=400.0)
    with pytest.raises(ValueError, match="speeds must be true or false"):
        RangeGuard(speeds="yes")
    with pytest.raises(ValueError, match="vz_max"):
        RangeGuard(vz_max=True)


@pytest.fixture(scope="module")
def bounded():
    """Generated trajectories (docs/spec.md defaults), most of which meet a soft range bound."""
    data = generate(40, seed=31)
    m, w = data[keys.MODE], data[keys.TURN_RATE]
    bound_turn = (m >= 2) & ((w.abs() - 8 * DEG).abs() < 1e-9)
    assert bound_turn.any(1).float().mean() > 0.5
    return data


def test_an_unreachable_guard_changes_nothing(bounded):
    far = {"outer": 1e9, "inner": 1.0, "speed_min": 1e-3, "speed_max": 1e9, "vz_max": 1e9}
    a = IMMEKF().track(bounded[:8])[keys.STATE]
    b = IMMEKF(guard=far).track(bounded[:8])[keys.STATE]
    torch.testing.assert_close(a, b, rtol=0, atol=1e-6)


def _excess_over_bound(data, mask, **methods):
    """Each method's position errors ``[N, T, 3]`` and its mean excess squared error over the clairvoyant
    bound's on the scans in ``mask [N, T]``."""
    from immnet.filters import ClairvoyantKF

    truth = data[keys.STATES]
    e = {name: position_error(meth.track(data)[keys.STATE], truth) for name, meth in methods.items()}
    bound = position_error(ClairvoyantKF().track(data)[keys.STATE], truth).pow(2).sum(-1)
    return e, {name: (err.pow(2).sum(-1) - bound)[mask].mean() for name, err in e.items()}


def test_the_guard_halves_the_imm_ekf_error_at_bound_turn_onsets(bounded):
    """The soft bounds are the generator's rules (docs/spec.md section 2): told them, the IMM-EKF's excess over
    the clairvoyant bound on the scans that start a bound turn falls by more than half, and its RMSE falls."""
    m, w = bounded[keys.MODE], bounded[keys.TURN_RATE]
    onset = torch.zeros_like(m, dtype=torch.bool)
    onset[:, 1:] = (m[:, 1:] != m[:, :-1]) & (m[:, 1:] >= 2) & ((w[:, 1:].abs() - 8 * DEG).abs() < 1e-9)
    e, excess = _excess_over_bound(bounded, onset, base=IMMEKF(), guard=IMMEKF(guard=True))
    assert excess["guard"] < 0.5 * excess["base"], excess
    assert rmse(e["guard"])["avg"] < rmse(e["base"])["avg"]


def test_the_speed_rules_cut_the_imm_ekf_error_after_speed_bound_turns(bounded):
    """A CA that leaves the speed bounds turns at 8 deg/s for one scan, then flies CV (docs/spec.md section 2):
    told this, the IMM-EKF's excess over the clairvoyant bound on the scan of that turn and the five after
    it falls by more than half (to about a quarter on these 40 trajectories, 13 such turns)."""
    m, w = bounded[keys.MODE], bounded[keys.TURN_RATE]
    turn = torch.zeros_like(m, dtype=torch.bool)  # CA, one scan of an 8 deg/s turn, CV (a range turn is longer)
    turn[:, 1:-1] = (m[:, :-2] == 1) & (m[:, 1:-1] >= 2) & ((w[:, 1:-1].abs() - 8 * DEG).abs() < 1e-9) & (m[:, 2:] == 0)
    after = turn.clone()
    for k in range(1, 6):
        after[:, k:] |= turn[:, :-k]
    assert int(turn.sum()) >= 5, "the data must hold speed-bound turns"
    _, excess = _excess_over_bound(bounded, after, range=IMMEKF(p_stay=0.999, guard={"speeds": False}),
                                   speed=IMMEKF(p_stay=0.999, guard=True))
    assert excess["speed"] < 0.5 * excess["range"], excess
