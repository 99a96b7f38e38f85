"""``scripts/r_estimate.py`` (docs/notebook/real-flights.md "Estimating r at 4.5-5.5 s"): its third divided
differences cancel CV and CA motion at any scan spacing, give an unbiased r^2 under measurement noise, and are the
network's own estimate."""

import runpy

import numpy as np
import pytest
import torch

from immnet import keys
from immnet.config import REPO_ROOT
from immnet.tracking import Tracker

SCRIPT = REPO_ROOT / "scripts" / "r_estimate.py"


@pytest.fixture(scope="module")
def script():
    return runpy.run_path(str(SCRIPT))


def _times(n, T, seed=0):
    rng = np.random.default_rng(seed)
    return np.cumsum(rng.uniform(4.5, 5.5, (n, T)), axis=1)


def test_third_differences_cancel_ca_motion_at_irregular_scans(script):
    t = _times(4, 30)
    p = 3_000.0 + 12.0 * t - 0.35 * t**2  # a constant acceleration: no noise, no sample
    s = script["third_difference_samples"](p, t)
    assert np.isnan(s[:, :3]).all()
    np.testing.assert_allclose(s[:, 3:], 0.0, atol=1e-12 * 3_000.0**2)


def test_third_differences_are_an_unbiased_r_squared(script):
    """White noise of std r: the samples' mean is r^2 (each a scaled chi-square of one degree of freedom, so the
    mean of 20,000 lies within 3 % of r^2), and their median is the chi-square's, 0.455 r^2."""
    r, t = 9.0, _times(200, 103, seed=1)
    noise = np.random.default_rng(2).normal(0.0, r, t.shape)
    s = script["third_difference_samples"](noise, t)[:, 3:]
    assert s.mean() == pytest.approx(r * r, rel=0.03)
    assert np.median(s) == pytest.approx(script["CHI2_MEDIAN"] * r * r, rel=0.05)


def test_they_are_the_networks_estimate(script):
    """After every scan, real-5s's running r^2 is ``(k0 r0^2 + sum of samples) / (k0 + count)`` of these samples."""
    t = _times(2, 15, seed=3)
    z = (np.stack([150.0 * t, 40.0 * t, 3_000.0 + 2.0 * t], -1) + np.random.default_rng(4).normal(0, 15.0, (2, 15, 3)))
    tracker = Tracker.pretrained("real-5s")
    gain = [m for m in tracker.net.modules() if hasattr(m, "k0")][0]
    samples = script["third_difference_samples"](z[..., 2], t)
    tracker.reset(2)
    gaps = np.diff(t, axis=1)
    for k in range(15):
        dt = torch.tensor(gaps[:, k - 1] if k else np.full(2, 5.0), dtype=torch.float32)
        tracker.step(torch.tensor(z[:, k], dtype=torch.float32), dt=dt)
        seen = samples[:, : k + 1]
        expect = (gain.k0 * gain.r0**2 + np.nansum(seen, 1)) / (gain.k0 + np.isfinite(seen).sum(1))
        got = tracker.carry.get(keys.NOISE_VAR).double().numpy().reshape(2, -1)
        np.testing.assert_allclose(got, np.broadcast_to(expect[:, None], got.shape), rtol=1e-4)
