"""Metrics of docs/spec.md section 5 against float64 numpy computations and closed forms."""

import numpy as np
import pytest
import torch

from immnet.evaluation import metrics as M


def _states(rng, n, t):
    return torch.from_numpy(rng.normal(size=(n, t, 9)) * 100.0)


@pytest.fixture
def case():
    rng = np.random.default_rng(0)
    n, t = 5, 37
    truth = _states(rng, n, t)
    est = truth + torch.from_numpy(rng.normal(size=(n, t, 9)) * np.array([1, 9, 9, 2, 9, 9, 3, 9, 9]))
    mode = torch.zeros(n, t, dtype=torch.long)
    mode[0, 10:] = 1          # one switch at 10
    mode[1, 5:] = 2           # switches at 5 and 12: windows overlap
    mode[1, 12:] = 3
    mode[2, 30:] = 1          # window clipped at T
    probs = torch.from_numpy(rng.random(size=(n, t, 4)))
    return est, truth, mode, probs


def _np_err(est, truth):
    return est.numpy()[..., [0, 3, 6]] - truth.numpy()[..., [0, 3, 6]]


def test_constant_error_gives_that_rmse():
    truth = torch.zeros(3, 50, 9, dtype=torch.float64)
    est = truth.clone()
    est[..., 0], est[..., 3], est[..., 6] = 1.5, -2.0, 4.0
    err = M.position_error(est, truth)
    for f in (M.rmse, M.rmse_pooled):
        r = f(err)
        assert r == pytest.approx({"x": 1.5, "y": 2.0, "z": 4.0, "avg": 2.5})
    assert torch.allclose(M.rmse_over_time(err), torch.tensor([1.5, 2.0, 4.0], dtype=torch.float64).expand(50, 3))


def test_rmse_is_mean_of_per_trajectory_rmse_and_pooled_differs(case):
    est, truth, _, _ = case
    e = _np_err(est, truth)
    per_traj = np.sqrt((e**2).mean(axis=1))  # [N, 3]
    want = per_traj.mean(axis=0)
    got = M.rmse(M.position_error(est, truth))
    assert [got["x"], got["y"], got["z"]] == pytest.approx(want, rel=1e-12)
    assert got["avg"] == pytest.approx(want.mean(), rel=1e-12)
    pooled = np.sqrt((e**2).mean(axis=(0, 1)))
    gp = M.rmse_pooled(M.position_error(est, truth))
    assert [gp["x"], gp["y"], gp["z"]] == pytest.approx(pooled, rel=1e-12)
    assert gp["avg"] >= got["avg"]  # Jensen: pooled >= mean of per-trajectory RMSEs (per axis)


def test_rmse_over_time(case):
    est, truth, _, _ = case
    e = _np_err(est, truth)
    want = np.sqrt((e**2).mean(axis=0))
    got = M.rmse_over_time(M.position_error(est, truth))
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-12)
    np.testing.assert_allclose(M.avg_curve(got).numpy(), np.sqrt((want**2).mean(axis=1)), rtol=1e-12)


def test_post_switch_mask_by_hand(case):
    _, _, mode, _ = case
    T = mode.shape[1]
    want = np.zeros(mode.shape, dtype=bool)
    m = mode.numpy()
    for n in range(m.shape[0]):
        for s in range(1, T):
            if m[n, s] != m[n, s - 1]:
                want[n, s : min(s + 20, T)] = True
    got = M.post_switch_mask(mode).numpy()
    np.testing.assert_array_equal(got, want)
    assert got[0].sum() == 20 and got[1].sum() == 12 + 20 - 5 and got[2].sum() == 7 and got[3].sum() == 0


def test_rmse_post_switch(case):
    est, truth, mode, _ = case
    e = _np_err(est, truth)
    mask = M.post_switch_mask(mode).numpy()
    want = np.sqrt((e[mask] ** 2).mean(axis=0))
    got = M.rmse_post_switch(M.position_error(est, truth), mode)
    assert [got["x"], got["y"], got["z"]] == pytest.approx(want, rel=1e-12)
    assert M.rmse_post_switch(M.position_error(est, truth), torch.zeros_like(mode)) is None


def test_mode_accuracy_and_confusion(case):
    _, _, mode, probs = case
    pred = probs.numpy().argmax(-1)
    want = np.zeros((4, 4), dtype=np.int64)
    for t_, p_ in zip(mode.numpy().ravel(), pred.ravel()):
        want[t_, p_] += 1
    np.testing.assert_array_equal(M.confusion(probs, mode).numpy(), want)
    assert M.mode_accuracy(probs, mode) == pytest.approx((pred == mode.numpy()).mean())
    perfect = torch.nn.functional.one_hot(mode, 4).double()
    assert M.mode_accuracy(perfect, mode) == 1.0


@pytest.mark.parametrize("batch", [1, 2, 5], ids=lambda b: f"batch{b}")
def test_accumulator_equals_whole_tensor_functions(case, batch):
    est, truth, mode, probs = case
    acc = M.MetricAccumulator()
    for s in range(0, est.shape[0], batch):
        acc.update(est[s : s + batch], truth[s : s + batch], mode[s : s + batch], probs[s : s + batch])
    r = acc.compute()
    err = M.position_error(est, truth)
    assert r["rmse"] == pytest.approx(M.rmse(err), rel=1e-12)
    assert r["rmse_pooled"] == pytest.approx(M.rmse_pooled(err), rel=1e-12)
    assert r["rmse_post_switch"] == pytest.approx(M.rmse_post_switch(err, mode), rel=1e-12)
    assert torch.allclose(r["rmse_over_time"], M.rmse_over_time(err))
    assert r["mode_accuracy"] == pytest.approx(M.mode_accuracy(probs, mode))
    assert torch.equal(r["confusion"], M.confusion(probs, mode))


# --- what is scored: truth padded with NaN, scans before the first detection, failures -------------
@pytest.fixture
def padded(case):
    """The case above as variable-length tracks: trajectory 0 ends at 25 (truth NaN, mode -1 after),
    trajectory 1 is first detected at 7, trajectory 3 has no truth at all, trajectory 4 no detection."""
    est, truth, mode, probs = (x.clone() for x in case)
    T = truth.shape[1]
    z = truth[..., [0, 3, 6]].clone()
    truth[0, 25:] = np.nan
    mode[0, 25:] = -1
    z[0, 25:] = np.nan
    z[1, :7] = np.nan
    est[1, :7] = np.nan  # a tracker has no estimate before the first detection
    z[1, 15] = np.nan  # a missed detection after the start is still scored
    truth[3] = np.nan
    mode[3] = -1
    z[4] = np.nan
    est[4] = np.nan
    valid = np.ones((5, T), bool)
    valid[0, 25:] = valid[1, :7] = valid[3] = valid[4] = False
    return est, truth, mode, probs, z, valid


def _np_metrics(est, truth, mode, probs, valid):
    """The metrics over the valid pairs only, in float64 numpy, by loops where that is clearer."""
    e = _np_err(est, truth)
    n, T = valid.shape
    rows = [np.sqrt((e[i][valid[i]] ** 2).mean(axis=0)) for i in range(n) if valid[i].any()]
    rmse = np.mean(rows, axis=0)
    pooled = np.sqrt((e[valid] ** 2).mean(axis=0))
    over_time = np.full((T, 3), np.nan)
    for t in range(T):
        if valid[:, t].any():
            over_time[t] = np.sqrt((e[valid[:, t], t] ** 2).mean(axis=0))
    m = mode.numpy()
    window = np.zeros((n, T), bool)
    for i in range(n):
        for s in range(1, T):
            if m[i, s] != m[i, s - 1] and m[i, s] >= 0 and m[i, s - 1] >= 0:
                window[i, s : s + 20] = True
    post = np.sqrt((e[window & valid] ** 2).mean(axis=0))
    lab = valid & (m >= 0)
    acc = (probs.numpy().argmax(-1)[lab] == m[lab]).mean()
    return rmse, pooled, over_time, post, acc


def test_nan_padded_truth_scores_only_the_scans_with_truth(padded):
    """Issue 20, item 3: truth padded with NaN after a track's end, a track without truth, and scans
    before a track's first detection are not scored; every metric equals a float64 numpy computation
    over the remaining pairs, and what was left out is counted."""
    est, truth, mode, probs, z, valid = padded
    acc = M.MetricAccumulator()
    for s in range(0, 5, 2):
        acc.update(est[s : s + 2], truth[s : s + 2], mode[s : s + 2], probs[s : s + 2], measurements=z[s : s + 2])
    r = acc.compute()
    rmse, pooled, over_time, post, accuracy = _np_metrics(est, truth, mode, probs, valid)
    assert [r["rmse"][a] for a in "xyz"] == pytest.approx(rmse, rel=1e-12)
    assert [r["rmse_pooled"][a] for a in "xyz"] == pytest.approx(pooled, rel=1e-12)
    assert [r["rmse_post_switch"][a] for a in "xyz"] == pytest.approx(post, rel=1e-12)
    np.testing.assert_allclose(r["rmse_over_time"].numpy(), over_time, rtol=1e-12)
    assert r["mode_accuracy"] == pytest.approx(accuracy, rel=1e-12)
    assert int(r["confusion"].sum()) == int((valid & (mode.numpy() >= 0)).sum())
    c = r["counts"]
    assert c["scored"] == valid.sum() and c["scans"] == 5 * 37
    assert c["without_truth"] == 12 + 37 and c["before_first_detection"] == 7 + 37
    assert c["excluded"] == 2 and c["nan_scans"] == 0 and c["diverged"] == 0
    assert torch.isnan(r["per_trajectory"][[3, 4]]).all() and torch.isfinite(r["per_trajectory"][[0, 1, 2]]).all()
    # the whole-tensor functions with the same mask agree
    mask = M.scored_mask(truth, z)
    np.testing.assert_array_equal(mask.numpy(), valid)
    err = M.position_error(est, truth)
    assert M.rmse(err, mask) == pytest.approx(r["rmse"], rel=1e-12)
    assert M.rmse_pooled(err, mask) == pytest.approx(r["rmse_pooled"], rel=1e-12)


def test_a_nan_estimate_after_the_start_is_a_failure_not_a_skip(padded):
    """Issue 20, item 3: an estimate that is NaN after its track has started is a tracker failure:
    counted (scans and trajectories) and reported as no number (None), never averaged away; the
    same estimate NaN before the first detection is skipped as the data say."""
    est, truth, mode, probs, z, valid = padded
    est[2, 20] = np.nan
    est[0, 3, 3] = np.inf
    acc = M.MetricAccumulator()
    acc.update(est, truth, mode, probs, measurements=z)
    r = acc.compute()
    assert r["counts"]["nan_scans"] == 2 and r["counts"]["diverged"] == 2
    assert r["rmse"] is None and r["rmse_pooled"] is None and r["rmse_post_switch"] is None
    assert r["mode_accuracy"] is None
    fin = torch.isfinite(r["per_trajectory"]).all(dim=-1)
    assert fin.tolist() == [False, True, False, False, False]  # 0, 2 diverged; 3, 4 had nothing scored


def test_nothing_to_score_is_an_error():
    """Issue 20, item 3: data with no scan holding both truth and a started track give no number."""
    truth = torch.full((2, 5, 9), np.nan, dtype=torch.float64)
    acc = M.MetricAccumulator()
    acc.update(torch.zeros(2, 5, 9), truth)
    with pytest.raises(ValueError, match="no trajectory has a scan"):
        acc.compute()


# --- the post-switch window in seconds (issue 22) -------------------------------------------------------
def test_post_switch_window_in_seconds_at_1s_is_the_20_scans(case):
    """At 1 s scans a 20 s window is exactly the 20-scan window: same mask, same numbers bit for bit."""
    est, truth, mode, probs = case
    ones = torch.ones(mode.shape, dtype=torch.float64)
    assert torch.equal(M.post_switch_mask(mode, intervals=ones), M.post_switch_mask(mode))
    err = M.position_error(est, truth)
    assert M.rmse_post_switch(err, mode, intervals=ones) == M.rmse_post_switch(err, mode)
    a, b = M.MetricAccumulator(), M.MetricAccumulator()
    a.update(est, truth, mode, probs)
    b.update(est, truth, mode, probs, intervals=ones)
    assert a.compute()["rmse_post_switch"] == b.compute()["rmse_post_switch"]


def test_post_switch_window_in_seconds_by_hand(case):
    """Irregular scans: a scan is in a window when it is at or after a switch and less than 20 s after it."""
    _, _, mode, _ = case
    rng = np.random.default_rng(3)
    iv = rng.uniform(0.5, 9.0, size=mode.shape)
    tau = np.cumsum(iv, axis=1)
    m = mode.numpy()
    want = np.zeros(m.shape, dtype=bool)
    for n in range(m.shape[0]):
        for s in range(1, m.shape[1]):
            if m[n, s] != m[n, s - 1]:
                want[n, s:] |= (tau[n, s:] - tau[n, s]) < 20.0
    got = M.post_switch_mask(mode, intervals=torch.from_numpy(iv)).numpy()
    np.testing.assert_array_equal(got, want)
    five = M.post_switch_mask(mode, intervals=torch.full(mode.shape, 5.0, dtype=torch.float64)).numpy()
    assert five[0].sum() == 4 and five[0, 10:14].all()  # 20 s at 5 s per scan: the switch scan and 3 more
    with pytest.raises(ValueError, match="intervals have shape"):
        M.post_switch_mask(mode, intervals=torch.ones(2, 3))


def test_scored_distance_is_the_euclidean_norm_on_the_mask_and_zero_off_it():
    """``scored_distance``: numpy's norm of each position error where scored, 0 where not (NaN errors included)."""
    g = torch.Generator().manual_seed(0)
    err = torch.randn(3, 7, 3, generator=g, dtype=torch.float64) * 100
    err[1, 2] = float("nan")
    mask = torch.rand(3, 7, generator=g) > 0.3
    mask[1, 2] = False
    got = M.scored_distance(err, mask).numpy()
    want = np.where(mask.numpy(), np.linalg.norm(np.nan_to_num(err.numpy()), axis=-1), 0.0)
    np.testing.assert_allclose(got, want, rtol=1e-15, atol=0)
