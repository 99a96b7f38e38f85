"""``FlightAugment``: a training batch turned about the radar site's vertical and measured again. Checked against
physical facts of the turned truth (range from the site, speeds, the vertical, the turn rate computed from the
turned velocity and acceleration), the law of the new noise (a chi-square), and the datamodule's hook (training
batches only, one view per training step)."""

import math
import types

import pytest
import torch

from immnet import keys
from immnet.data.augment import ROLL_S, FlightAugment, _turn_phase, add_turns
from immnet.data.contract import NO_LABEL
from immnet.data.datamodule import LASTDataModule
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.data.storage import write_dataset


@pytest.fixture(scope="module")
def batch():
    td = generate(64, seed=5, spec=DataSpec(T=50, min_segment=10, p_miss=0.1))
    return td.apply(lambda v: v.float() if v.is_floating_point() else v)


def _turn_rate(x: torch.Tensor) -> torch.Tensor:
    vx, vy, ax, ay = x[..., 1], x[..., 4], x[..., 2], x[..., 5]
    return (vx * ay - vy * ax) / (vx * vx + vy * vy)


def test_rotation_keeps_what_a_turn_about_the_site_keeps(batch):
    out = FlightAugment(rotate=True, renoise=False)(batch, step=3)
    x, y = batch[keys.STATES].double(), out[keys.STATES].double()
    for idx in ((0, 3), (1, 4), (2, 5)):  # range from the site's vertical, horizontal speed, acceleration
        torch.testing.assert_close(y[..., idx].norm(dim=-1), x[..., idx].norm(dim=-1), rtol=1e-6, atol=1e-3)
    assert torch.equal(y[..., 6:], x[..., 6:])  # the vertical
    assert (y[..., 0] - x[..., 0]).abs().max() > 1.0  # and it did turn
    torch.testing.assert_close(_turn_rate(y), _turn_rate(x), rtol=1e-6, atol=1e-7)  # the turn rate, sense kept
    assert torch.equal(out[keys.MODE], batch[keys.MODE])
    # without new noise the measurements turn with the truth: each residual's length is kept
    nu0 = batch[keys.MEASUREMENTS].double() - x[..., [0, 3, 6]]
    nu1 = out[keys.MEASUREMENTS].double() - y[..., [0, 3, 6]]
    assert torch.equal(torch.isnan(nu1), torch.isnan(nu0))
    ok = ~torch.isnan(nu0[..., 0])
    torch.testing.assert_close(nu1[ok].norm(dim=-1), nu0[ok].norm(dim=-1), rtol=0, atol=2e-2)
    assert torch.equal(out[keys.R], batch[keys.R])


def test_new_noise_has_the_drawn_r_and_keeps_the_missed_scans(batch):
    aug = FlightAugment(rotate=True, renoise=True, r_range=(2.0, 9.0))
    out = aug(batch, step=11)
    r = out[keys.R].double()
    assert r.min() >= 2.0 and r.max() <= 9.0 and not torch.equal(out[keys.R], batch[keys.R])
    z, x = out[keys.MEASUREMENTS].double(), out[keys.STATES].double()
    assert torch.equal(torch.isnan(z), torch.isnan(batch[keys.MEASUREMENTS]))
    e = (z - x[..., [0, 3, 6]]) / r[:, None, None]
    e = e[~torch.isnan(e)]
    n = e.numel()
    # sum of squares of n standard normals: mean n, std sqrt(2n); 5 standard deviations
    assert abs(float(e.square().sum()) - n) < 5 * math.sqrt(2 * n)
    assert abs(float(e.mean())) < 5 / math.sqrt(n)
    # without r_range each track keeps its own r
    own = FlightAugment(rotate=False, renoise=True)(batch, step=11)
    assert torch.equal(own[keys.R], batch[keys.R]) and torch.equal(own[keys.STATES], batch[keys.STATES])
    assert not torch.equal(own[keys.MEASUREMENTS].nan_to_num(), batch[keys.MEASUREMENTS].nan_to_num())


def test_one_view_per_step(batch):
    aug = FlightAugment(r_range=(1.0, 7.0), seed=4)
    a, b, c = aug(batch, 7), aug(batch, 7), aug(batch, 8)
    assert torch.equal(a[keys.STATES], b[keys.STATES]) and torch.equal(a[keys.MEASUREMENTS].nan_to_num(),
                                                                     b[keys.MEASUREMENTS].nan_to_num())
    assert not torch.equal(a[keys.STATES], c[keys.STATES])
    assert not torch.equal(a[keys.STATES], FlightAugment(r_range=(1.0, 7.0), seed=5)(batch, 7)[keys.STATES])
    same = FlightAugment(rotate=False, renoise=False)(batch, 7)
    assert same is batch  # nothing asked, nothing changed
    assert torch.equal(batch[keys.STATES], generate(64, seed=5, spec=DataSpec(T=50, min_segment=10, p_miss=0.1))[keys.STATES].float())


def test_bad_settings_are_refused_by_name(batch):
    with pytest.raises(ValueError, match="holds no 'r': give r_range"):
        FlightAugment()(batch.exclude(keys.R), 0)
    assert FlightAugment(r_range=(1.0, 2.0))(batch.exclude(keys.R), 0)[keys.R].shape == batch[keys.R].shape
    with pytest.raises(ValueError, match="r_range must be"):
        FlightAugment(r_range=(5.0, 1.0))
    with pytest.raises(ValueError, match="r_range must be"):
        FlightAugment(r_range=(0.0, 1.0))
    with pytest.raises(ValueError, match="needs renoise=True"):
        FlightAugment(renoise=False, r_range=(1.0, 7.0))


def test_the_datamodule_augments_training_batches_only(tmp_path):
    write_dataset(tmp_path / "d", 20, seed=6, spec=DataSpec(T=30, min_segment=10))
    dm = LASTDataModule(str(tmp_path / "d"), batch_size=8, augment=FlightAugment(r_range=(1.0, 7.0)))
    b = next(iter(dm.train_dataloader()))
    dm.trainer = types.SimpleNamespace(training=True, global_step=2)
    seen = dm.on_after_batch_transfer(b, 0)
    assert torch.equal(seen[keys.STATES], FlightAugment(r_range=(1.0, 7.0))(b, 2)[keys.STATES])
    assert not torch.equal(seen[keys.STATES], b[keys.STATES])
    dm.trainer = types.SimpleNamespace(training=False, global_step=2)  # validation, test: as stored
    assert dm.on_after_batch_transfer(b, 0) is b
    assert LASTDataModule(str(tmp_path / "d")).on_after_batch_transfer(b, 0) is b


# --- added turns (FlightAugment(turns=...), add_turns) ---------------------------------------------------------------

def _straight(t: torch.Tensor, speed: float = 150.0) -> torch.Tensor:
    """Level flight due east at ``speed`` through (1000, 0, 3000) at ``t = 0``: states ``[1, T, 9]`` (float64)."""
    x = torch.zeros(1, t.numel(), 9, dtype=torch.float64)
    x[..., 0], x[..., 1], x[..., 6] = 1000.0 + speed * t, speed, 3000.0
    return x


@pytest.mark.parametrize("jitter", [False, True])
def test_an_added_turn_flies_a_straight_flight_round_a_circle(jitter):
    g = torch.Generator().manual_seed(0)
    wobble = torch.rand(40, generator=g, dtype=torch.float64) - 0.5
    steps = 5.0 + (wobble if jitter else torch.zeros_like(wobble))
    t = torch.cat([torch.zeros(1, dtype=torch.float64), steps.cumsum(0)])
    intervals = torch.cat([torch.full((1,), 5.0, dtype=torch.float64), steps])[None]
    w = math.radians(2.0)
    y = add_turns(_straight(t), intervals, torch.tensor([[1e6]], dtype=torch.float64),
                  torch.tensor([[w, w]], dtype=torch.float64))[0]
    radius = 150.0 / w  # 4.3 km: the closed form of a constant-rate turn from heading east
    torch.testing.assert_close(y[:, 0], 1000.0 + radius * torch.sin(w * t), rtol=0, atol=0.05)
    torch.testing.assert_close(y[:, 3], radius * (1 - torch.cos(w * t)), rtol=0, atol=0.05)
    torch.testing.assert_close(y[:, 1], 150.0 * torch.cos(w * t), rtol=0, atol=1e-9)
    torch.testing.assert_close(y[:, 4], 150.0 * torch.sin(w * t), rtol=0, atol=1e-9)
    torch.testing.assert_close(y[:, [2, 5]].norm(dim=-1), torch.full_like(t, 150.0 * w), rtol=0, atol=1e-9)  # v w
    torch.testing.assert_close(_turn_rate(y), torch.full_like(t, w), rtol=0, atol=1e-12)
    assert torch.equal(y[:, 6:], _straight(t)[0, :, 6:])


def test_the_rate_rolls_between_segments_and_the_heading_is_its_integral():
    tau = torch.linspace(0.0, 120.0, 4801, dtype=torch.float64)[None]  # 0.025 s
    boundaries = torch.tensor([[30.0, 70.0]], dtype=torch.float64)
    rates = torch.tensor([[0.0, 0.04, -0.02]], dtype=torch.float64)
    w, phi = _turn_phase(tau, boundaries, rates)
    expected = torch.where(tau < 30, 0.0, torch.where(tau < 30 + ROLL_S, 0.04 * (tau - 30) / ROLL_S, 0.04))
    expected = torch.where(tau < 70, expected, torch.where(tau < 70 + ROLL_S, 0.04 - 0.06 * (tau - 70) / ROLL_S, -0.02))
    torch.testing.assert_close(w, expected, rtol=0, atol=1e-12)
    trapezoid = torch.cat([torch.zeros(1, 1, dtype=torch.float64),
                           (0.5 * (w[:, 1:] + w[:, :-1]) * tau.diff(dim=-1)).cumsum(-1)], -1)
    torch.testing.assert_close(phi, trapezoid, rtol=0, atol=1e-9)
    # the acceleration is the derivative of the velocity, through the roll-ins too (0.1 s scans, central
    # differences: off by at most a quarter step times the jump of the jerk at a roll's ends, 150 * 0.012 / 40)
    t = torch.arange(1201, dtype=torch.float64) / 10
    step = torch.full((1, 1201), 0.1, dtype=torch.float64)
    y = add_turns(_straight(t), step, boundaries, rates)[0]
    for v, a in ((1, 2), (4, 5)):
        central = (y[2:, v] - y[:-2, v]) / 0.2
        torch.testing.assert_close(central, y[1:-1, a], rtol=0, atol=0.05)
        # and the positions move with it: each step the cubic through its ends' velocity and acceleration
        cubic = 0.05 * (y[1:, v] + y[:-1, v]) + 0.01 / 12 * (y[:-1, a] - y[1:, a])
        torch.testing.assert_close(y[1:, v - 1] - y[:-1, v - 1], cubic, rtol=0, atol=1e-6)
    # no added rate: the flight as recorded
    assert torch.equal(add_turns(_straight(t), step, boundaries, torch.zeros_like(rates)), _straight(t))


@pytest.fixture(scope="module")
def unlabelled(batch):
    out = batch.clone()
    out[keys.MODE] = torch.full_like(out[keys.MODE], NO_LABEL)
    return out


def test_turns_keep_each_flights_speeds_and_vertical_and_bank_at_most_as_asked(unlabelled):
    aug = FlightAugment(rotate=False, renoise=True, turns=0.5, turn_bank=(10.0, 30.0), seed=2)
    out = aug(unlabelled, step=9)
    x, y = unlabelled[keys.STATES].double(), out[keys.STATES].double()
    torch.testing.assert_close(y[..., [1, 4]].norm(dim=-1), x[..., [1, 4]].norm(dim=-1), rtol=1e-6, atol=1e-3)
    assert torch.equal(y[..., 6:], x[..., 6:])
    assert torch.equal(y[:, 0, [0, 3]], x[:, 0, [0, 3]])  # scan 0 stays put
    turned = (y - x).abs().amax((1, 2)) > 1.0
    assert 16 <= int(turned.sum()) <= 48  # half of 64, give or take four standard deviations
    # the added rate is a coordinated turn banked at most 30 deg at the track's mean speed
    mean_speed = x[..., [1, 4]].norm(dim=-1).mean(-1, keepdim=True)
    added = _turn_rate(y) - _turn_rate(x)
    assert bool((added.abs() <= 9.80665 * math.tan(math.radians(30)) / mean_speed + 1e-6).all())
    assert float(added[turned].abs().max()) > 9.80665 * math.tan(math.radians(10)) / float(mean_speed.max())
    torch.testing.assert_close(out[keys.TURN_RATE].double(), _turn_rate(y), rtol=1e-5, atol=1e-6)
    # the measurements are new draws about the new truth, with each track's own r
    e = (out[keys.MEASUREMENTS].double() - y[..., [0, 3, 6]]) / out[keys.R].double()[:, None, None]
    e = e[~torch.isnan(e)]
    assert abs(float(e.square().sum()) - e.numel()) < 5 * math.sqrt(2 * e.numel())
    # the views are those drawn without turns: tracks left straight are exactly the turns=0 view
    plain = FlightAugment(rotate=True, renoise=True, seed=2)(unlabelled, step=9)
    both = FlightAugment(rotate=True, renoise=True, turns=0.5, seed=2)(unlabelled, step=9)
    keep = ~turned
    assert torch.equal(both[keys.STATES][keep], plain[keys.STATES][keep])
    assert torch.equal(both[keys.MEASUREMENTS][keep].nan_to_num(), plain[keys.MEASUREMENTS][keep].nan_to_num())
    assert torch.equal(both[keys.R], plain[keys.R])


def test_turn_settings_and_labelled_batches_are_refused_by_name(batch):
    with pytest.raises(ValueError, match="without mode labels"):
        FlightAugment(turns=0.5)(batch, 0)
    with pytest.raises(ValueError, match="turns is the share"):
        FlightAugment(turns=1.5)
    with pytest.raises(ValueError, match="needs renoise=True"):
        FlightAugment(renoise=False, turns=0.5)
    with pytest.raises(ValueError, match="turn_bank must be"):
        FlightAugment(turns=0.5, turn_bank=(30.0, 10.0))
    with pytest.raises(ValueError, match="below 90"):
        FlightAugment(turns=0.5, turn_bank=(10.0, 90.0))
    with pytest.raises(ValueError, match="turn_segment must be"):
        FlightAugment(turns=0.5, turn_segment=(0.0, 10.0))
