"""Metrics of SPEC.md section 5 against float64 numpy computations and closed forms."""

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
