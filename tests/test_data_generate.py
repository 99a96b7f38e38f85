"""3D-LAST generator against physics: closed forms, the turn ODE, the noise structure, the bounds."""

import math

import numpy as np
import pytest
import torch

from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.motion import DEG, ca_matrix, ct_matrix, cv_matrix

CV, CA, CTP, CTM = 0, 1, 2, 3
NO_BOUNDS = dict(  # soft and hard bounds out of the way: the labels are the schedule
    bound_range_outer=1e12, bound_range_inner=0.0, bound_speed_min=-1.0, bound_speed_max=1e12,
    bound_vz=1e12, hard_range_min=0.0, hard_range_max=1e15, hard_speed_max=1e12,
    hard_alt_min=-1e15, hard_alt_max=1e15,
)


@pytest.fixture(scope="module")
def data():
    return generate(1000, seed=11)


def _runs(labels):
    """Run-length encoding of one label sequence: list of (mode, length)."""
    change = np.flatnonzero(np.diff(labels)) + 1
    starts = np.r_[0, change]
    ends = np.r_[change, len(labels)]
    return [(int(labels[s]), int(e - s)) for s, e in zip(starts, ends)]


def _residual(x_prev, x_next, F):
    e = x_next - np.einsum("...ij,...j->...i", F, x_prev)
    return e


def _in_range_of_G(e, dt=1.0, tol=1e-8):
    """Residual of x_t - F x_{t-1} is G n: acceleration residual 0, position residual dt/2 * velocity residual.

    The tolerance is float64 round-off on positions of tens of km; a CT step at 1 deg/s and 30 m/s
    differs from CA with its centripetal acceleration by ~1e-5 m, far above it.
    """
    acc_ok = np.abs(e[..., [2, 5, 8]]).max(-1) < tol
    pos_ok = np.abs(e[..., [0, 3, 6]] - 0.5 * dt * e[..., [1, 4, 7]]).max(-1) < tol * 10
    return acc_ok & pos_ok


def test_shapes_dtypes(data):
    assert data.batch_size == torch.Size([1000])
    assert data["states"].shape == (1000, 400, 9) and data["states"].dtype == torch.float64
    assert data["measurements"].shape == (1000, 400, 3) and data["measurements"].dtype == torch.float64
    assert data["mode"].shape == (1000, 400) and data["mode"].dtype == torch.int64
    assert data["turn_rate"].shape == (1000, 400) and data["turn_rate"].dtype == torch.float64
    assert data["r"].shape == (1000,) and data["dt"].shape == (1000,)


def test_labels_match_the_motion_applied_at_every_step(data):
    x = data["states"].numpy()
    lab = data["mode"].numpy()
    w = data["turn_rate"].numpy()
    xp, xn, m, wt = x[:, :-1], x[:, 1:], lab[:, 1:], w[:, 1:]
    prev_lab = lab[:, :-1]
    # CV
    e_cv = _residual(xp, xn, cv_matrix(1.0).numpy())
    ok_cv = _in_range_of_G(e_cv)
    # CA: at the first CA step the new acceleration is written into x_{t-1}; later it must stay constant
    xp_ca = xp.copy()
    start = prev_lab != CA
    for a in (2, 5, 8):
        xp_ca[..., a] = np.where(start, xn[..., a], xp[..., a])
    e_ca = _residual(xp_ca, xn, ca_matrix(1.0).numpy())
    ok_ca = _in_range_of_G(e_ca) & (np.abs(xn[..., [2, 5]]).max(-1) > 1e-3)
    # CT with the labelled turn rate (and with the opposite one), at the CT steps and at the others
    is_ct = (m == CTP) | (m == CTM)

    def ok_ct(mask, sign):
        F = ct_matrix(torch.from_numpy(sign * wt[mask]), 1.0).numpy()
        return _in_range_of_G(_residual(xp[mask], xn[mask], F))

    assert ok_cv[m == CV].all()
    assert ok_ca[m == CA].all()
    assert ok_ct(is_ct, 1.0).all()
    # exactly the labelled mode
    assert not ok_cv[m == CA].any() and not ok_cv[is_ct].any()
    assert not ok_ca[is_ct].any()
    assert not ok_ct(is_ct, -1.0).any()
    # turn rates: 0 for CV/CA, sign by mode, |w| in [1, 10] deg/s (bound turns at 8)
    assert (wt[~is_ct] == 0).all()
    assert (wt[m == CTP] > 0).all() and (wt[m == CTM] < 0).all()
    aw = np.abs(wt[is_ct]) / DEG
    assert aw.min() >= 1 - 1e-9 and aw.max() <= 10 + 1e-9
    # t = 0: a CT first mode carries the centripetal acceleration, a CA one its drawn acceleration
    x0, m0, w0 = x[:, 0], lab[:, 0], w[:, 0]
    ct0 = m0 >= CTP
    np.testing.assert_allclose(x0[ct0, 2], -w0[ct0] * x0[ct0, 4], atol=1e-9)
    np.testing.assert_allclose(x0[ct0, 5], w0[ct0] * x0[ct0, 1], atol=1e-9)
    ah = np.hypot(x0[m0 == CA, 2], x0[m0 == CA, 5])
    assert ah.min() >= 0.5 - 1e-9 and ah.max() <= 3 + 1e-9
    assert (np.abs(x0[m0 == CA, 8]) <= 0.3).all()
    assert (x0[m0 == CV][:, [2, 5, 8]] == 0).all()


def test_every_trajectory_within_bounds(data):
    x = data["states"].numpy()
    rho = np.hypot(x[..., 0], x[..., 3])
    hs = np.hypot(x[..., 1], x[..., 4])
    assert rho.min() >= 0.5 * 1852 and rho.max() <= 20 * 1852
    assert hs.max() <= 340
    assert x[..., 6].min() >= 100 and x[..., 6].max() <= 15000
    r = data["r"].numpy()
    assert r.min() >= 1 and r.max() <= 7
    assert (data["dt"] == 1.0).all()


def test_measurement_noise_has_std_r(data):
    z = data["measurements"].numpy()
    x = data["states"].numpy()[..., [0, 3, 6]]
    r = data["r"].numpy()
    normed = (z - x) / r[:, None, None]
    assert abs(normed.std() - 1) < 0.01 and abs(normed.mean()) < 0.01


def test_schedule_three_segments_min_length_modes_differ():
    spec = DataSpec(**NO_BOUNDS)
    lab = generate(800, seed=3, spec=spec)["mode"].numpy()
    firsts = []
    for row in lab:
        runs = _runs(row)
        assert len(runs) == 3
        assert min(length for _, length in runs) >= 40
        assert all(a != b for (a, _), (b, _) in zip(runs, runs[1:]))
        firsts.append(runs[0][0])
    counts = np.bincount(firsts, minlength=4) / len(firsts)
    assert np.abs(counts - 0.25).max() < 0.06


def test_soft_bounds_make_turns_and_cv():
    # a target starting at 32.5 km flying outward must turn toward the radar at 8 deg/s
    spec = DataSpec(range_min=32_500.0, range_max=32_900.0, T=120, min_segment=40)
    d = generate(400, seed=5, spec=spec, single_mode="cv")
    lab, w = d["mode"].numpy(), d["turn_rate"].numpy()
    turned = (lab >= CTP).any(1)
    assert turned.mean() > 0.3
    bound_w = np.abs(w[lab >= CTP]) / DEG
    np.testing.assert_allclose(bound_w, 8.0, rtol=1e-12)
    x = d["states"].numpy()
    for i in np.flatnonzero(turned)[:50]:
        runs = _runs(lab[i])
        assert runs[-1][0] == CV  # CV after the turn until the (absent) next switch
        end = runs[0][1] + runs[1][1]  # first step after the turn
        v = x[i, end - 1]
        rho = math.hypot(v[0], v[3])
        vr = (v[0] * v[1] + v[3] * v[4]) / rho
        outer = rho > 20_000  # else the target crossed to the inner bound
        u = x[i, runs[0][1] - 1]  # where the turn was triggered
        assert math.hypot(u[0], u[3]) > 33_000 if outer else math.hypot(u[0], u[3]) < 4_000
        # heading points back by >= 30 deg: radial speed beyond half the speed, the other way
        assert (vr < -0.5 * math.hypot(v[1], v[4])) if outer else (vr > 0.5 * math.hypot(v[1], v[4]))


@pytest.mark.parametrize("mode", ["ct+", "ct-"])
def test_ct_keeps_speed_and_matches_turn_ode(mode):
    spec = DataSpec(sigma_q=0.0, T=60, min_segment=20)
    d = generate(200, seed=7, spec=spec, single_mode=mode)
    x, lab, w = d["states"].numpy(), d["mode"].numpy(), d["turn_rate"].numpy()
    hs = np.hypot(x[..., 1], x[..., 4])
    np.testing.assert_allclose(hs, hs[:, :1].repeat(60, 1), rtol=1e-12)
    assert (lab[:, 0] == (CTP if mode == "ct+" else CTM)).all()
    # RK4 on l' = v, v' = w e_z x v over one dt, 1000 sub-steps
    sel = lab[:, 1] == lab[:, 0]
    p, v, om = x[sel, 0][:, [0, 3]].copy(), x[sel, 0][:, [1, 4]].copy(), w[sel, 1]

    def f(p_, v_):
        return v_, np.stack([-om * v_[:, 1], om * v_[:, 0]], 1)

    h = 1.0 / 1000
    for _ in range(1000):
        k1 = f(p, v)
        k2 = f(p + h / 2 * k1[0], v + h / 2 * k1[1])
        k3 = f(p + h / 2 * k2[0], v + h / 2 * k2[1])
        k4 = f(p + h * k3[0], v + h * k3[1])
        p = p + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        v = v + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
    x1 = x[sel, 1]
    np.testing.assert_allclose(x1[:, [0, 3]], p, atol=1e-6)
    np.testing.assert_allclose(x1[:, [1, 4]], v, atol=1e-8)
    np.testing.assert_allclose(x1[:, [2, 5]], np.stack([-om * v[:, 1], om * v[:, 0]], 1), atol=1e-8)
    np.testing.assert_allclose(x1[:, 6], x[sel, 0, 6] + x[sel, 0, 7], atol=1e-9)  # z as CV


def test_ca_matches_closed_form_kinematics():
    spec = DataSpec(sigma_q=0.0, T=80, min_segment=20)
    d = generate(200, seed=8, spec=spec, single_mode="ca")
    x, lab = d["states"].numpy(), d["mode"].numpy()
    assert (lab[:, 0] == CA).all()
    n_ca = np.argmin(np.c_[lab == CA, np.zeros(len(lab), bool)], axis=1)  # length of the leading CA run
    assert (n_ca > 10).mean() > 0.5
    for i in np.flatnonzero(n_ca > 10)[:100]:
        t = np.arange(n_ca[i])
        x0 = x[i, 0]
        for p, vv, a in ((0, 1, 2), (3, 4, 5), (6, 7, 8)):
            np.testing.assert_allclose(x[i, t, p], x0[p] + x0[vv] * t + 0.5 * x0[a] * t**2, rtol=1e-10, atol=1e-6)
            np.testing.assert_allclose(x[i, t, vv], x0[vv] + x0[a] * t, atol=1e-8)
            np.testing.assert_allclose(x[i, t, a], x0[a], atol=0)


@pytest.mark.parametrize("mode", ["cv", "ca", "ct+", "ct-"])
def test_single_mode_gives_one_segment_of_that_mode(mode):
    d = generate(300, seed=9, spec=DataSpec(T=100, min_segment=20, **NO_BOUNDS), single_mode=mode)
    assert (d["mode"] == ["cv", "ca", "ct+", "ct-"].index(mode)).all()


def test_reproducible_bytes():
    spec = DataSpec(T=60, min_segment=20)
    a, b, c = generate(300, 1, spec), generate(300, 1, spec), generate(300, 2, spec)
    for k in a.keys():
        assert a[k].numpy().tobytes() == b[k].numpy().tobytes()
    assert not torch.equal(a["states"], c["states"])


def test_bad_arguments():
    with pytest.raises(ValueError, match="cv, ca, ct\\+, ct-"):
        generate(10, 0, single_mode="ct")
    with pytest.raises(ValueError, match="positive"):
        generate(0, 0)
    with pytest.raises(ValueError, match="unknown DataSpec field"):
        DataSpec.from_dict({"T": 10, "bogus": 1})


# --- any scan interval (issue 22) -----------------------------------------------------------------
def _digest(td) -> str:
    import hashlib

    h = hashlib.sha256()
    for k in ("states", "measurements", "mode", "turn_rate", "r", "dt"):
        h.update(td[k].contiguous().numpy().tobytes())
    return h.hexdigest()


def test_fixed_interval_bytes_are_those_before_scan_times():
    """dt_jitter = 0 draws nothing new: the digests were computed with the generator of commit 616cff5
    (before dt_jitter existed) on these very calls; a changed draw order or arithmetic changes them."""
    assert _digest(generate(64, 7)) == "fc776a8ab8a33ec1204b14319bdacbadbc068d2822503b35a9abb38c4605a795"
    assert _digest(generate(64, 7, DataSpec(T=120, min_segment=30, p_miss=0.1))) == (
        "f437aee80a5dfb594d24d63911560c708754b1d2d0e306277c90a3c1e756f557")
    assert _digest(generate(16, 3, single_mode="ct+")) == (
        "3471716a6223152c2291952210b24d355daf030dc0f87712af6bd3c3db3661a3")


def test_fixed_interval_scan_times_are_k_dt():
    td = generate(8, 1, DataSpec(T=60, dt=5.0, min_segment=10))
    assert td["t"].dtype == torch.float64 and td["t"].shape == (8, 60)
    assert torch.equal(td["t"], (torch.arange(60, dtype=torch.float64) * 5.0).expand(8, 60))
    assert torch.equal(td["dt"], torch.full((8,), 5.0, dtype=torch.float64))


def test_jittered_intervals_reproducible_and_inside_their_range():
    spec = DataSpec(T=80, dt=5.0, dt_jitter=0.5, min_segment=10)
    a, b = generate(50, 3, spec), generate(50, 3, spec)
    assert _digest(a) == _digest(b) and torch.equal(a["t"], b["t"])
    iv = a["t"].diff(dim=1)
    assert torch.equal(a["t"][:, 0], torch.zeros(50, dtype=torch.float64))
    assert iv.min() >= 4.5 and iv.max() <= 5.5
    assert iv.std() > 0.2  # U[4.5, 5.5] has std 0.29: the intervals are drawn, not fixed
    assert abs(iv.mean().item() - 5.0) < 0.02  # 3950 draws: std of the mean 0.005
    assert torch.equal(a["dt"], torch.full((50,), 5.0, dtype=torch.float64))  # the nominal (mean) interval
    assert _digest(generate(50, 4, spec)) != _digest(a)


def test_cv_truth_advances_by_velocity_times_each_interval():
    """Physical check: with no process noise a CV trajectory moves by v * dt_k at every step k."""
    spec = DataSpec(T=60, dt=5.0, dt_jitter=0.5, min_segment=10, sigma_q=0.0)
    td = generate(40, 5, spec, single_mode="cv")
    x, iv = td["states"], td["t"].diff(dim=1)
    cv = (td["mode"][:, 1:] == 0)  # soft bounds may turn a trajectory; score the CV steps
    assert cv.float().mean() > 0.8
    for pos, vel in ((0, 1), (3, 4), (6, 7)):
        step = x[:, 1:, pos] - x[:, :-1, pos]
        want = x[:, :-1, vel] * iv
        assert torch.allclose(step[cv], want[cv], rtol=0, atol=1e-9)
        assert torch.equal(x[:, 1:, vel][cv], x[:, :-1, vel][cv])  # velocity constant in CV


def test_dt_jitter_must_be_below_dt():
    for bad in (-0.1, 1.0, 2.0):
        with pytest.raises(ValueError, match="dt_jitter"):
            DataSpec(dt=1.0, dt_jitter=bad)
    assert DataSpec.from_dict({"dt": 5, "dt_jitter": 0.5}).dt_jitter == 0.5


@pytest.mark.parametrize("dt", [1.0, 0.1, 4.8, 5.0])
def test_scans_at_k_dt_read_as_the_same_data_without_t(dt, tmp_path):
    """t = k dt rounds (0.1 s: differences 0.1 +- 6e-15; a directory stores dt float32): scan_intervals
    reads it exactly as the data without t, the nominal dt at every scan, in memory and from disk."""
    from immnet.data.storage import as_batch, load_dataset, write_dataset
    from immnet.data.times import regular, scan_intervals

    spec = DataSpec(T=400, dt=dt, min_segment=40)
    td = generate(4, 0, spec)
    assert torch.equal(scan_intervals(td), scan_intervals(td.exclude("t")))
    disk = as_batch(load_dataset(write_dataset(tmp_path / "d", 4, 0, spec))[0])
    assert torch.equal(scan_intervals(disk), scan_intervals(disk.exclude("t"))) and regular(scan_intervals(disk))
    jit = generate(4, 0, DataSpec(T=400, dt=dt, dt_jitter=dt / 10, min_segment=40))
    iv = scan_intervals(jit)
    assert torch.allclose(iv[:, 1:], jit["t"].diff(dim=1), rtol=0, atol=0) and not regular(iv)  # drawn: kept
