"""``FlightAugment``: a training batch turned about the radar site's vertical and measured again. Checked against
physical facts of the turned truth (range from the site, speeds, the vertical, the turn rate computed from the
turned velocity and acceleration), the law of the new noise (a chi-square), and the datamodule's hook (training
batches only, one view per training step)."""

import math
import types

import pytest
import torch

from immnet import keys
from immnet.data.augment import FlightAugment
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
