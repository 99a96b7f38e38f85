"""Many targets: GOSPA and the identity metrics (against Stone Soup and hand counts), the multi-target tracker's
filter (against the single-target IMMs), association on hand-made scenes, clutter, and a Monte Carlo check against
the IMM told the association (docs/multi-target.md, "The tracker")."""

from __future__ import annotations

import datetime

from dataclasses import asdict

import numpy as np
import pytest

from immnet.evaluation.gospa import gospa, track_metrics


# --- GOSPA ---------------------------------------------------------------------------------------------------------

def test_gospa_matches_stone_soup_on_random_sets():
    """Stone Soup 1.9.1's ``GOSPAMetric.compute_gospa_metric``: the distance, its three parts (p-th power sums) and the
    truth-to-estimate assignment, on random sets of 0 to 6 points each (empty truth, empty estimates), to 1e-9."""
    from stonesoup.metricgenerator.ospametric import GOSPAMetric
    from stonesoup.types.state import State

    rng = np.random.default_rng(0)
    stamp = datetime.datetime(2024, 1, 1)
    checked = {"empty truth": 0, "empty estimates": 0, "both": 0}
    for c, p in ((200.0, 2.0), (150.0, 1.0), (300.0, 3.0)):
        metric = GOSPAMetric(c=c, p=p)
        for _ in range(120):
            n, m = (int(v) for v in rng.integers(0, 7, 2))
            if n == 0 and m == 0:
                continue  # Stone Soup needs a timestamp from some state (the empty case is checked below)
            X, Y = rng.uniform(0, 500, (n, 3)), rng.uniform(0, 500, (m, 3))
            ref, ref_assign = metric.compute_gospa_metric([State(y.reshape(3, 1), timestamp=stamp) for y in Y],
                                                          [State(x.reshape(3, 1), timestamp=stamp) for x in X])
            ours = gospa(X, Y, c=c, p=p)
            scale = max(1.0, ref.value["distance"] ** p)
            for key in ("localisation", "missed", "false"):
                assert abs(ours[key] - ref.value[key]) <= 1e-9 * scale, (key, n, m)
            assert abs(ours["gospa"] - ref.value["distance"]) <= 1e-9 * max(1.0, ref.value["distance"])
            if n and m:
                assert (ours["assignment"] == np.asarray(ref_assign)).all()
                checked["both"] += 1
            else:
                checked["empty truth" if n == 0 else "empty estimates"] += 1
    assert min(checked.values()) > 5, checked
    empty = gospa(np.zeros((0, 3)), np.zeros((0, 3)))
    assert empty["gospa"] == 0.0 and len(empty["assignment"]) == 0


def test_gospa_by_hand():
    """Two truths, three estimates: one pair at 30 m, one at 250 m (beyond c = 200: a missed and a false target)."""
    X = np.array([[0.0, 0, 0], [1000, 0, 0]])
    Y = np.array([[30.0, 0, 0], [1250, 0, 0], [5000, 0, 0]])
    g = gospa(X, Y, c=200.0, p=2.0)
    assert g["localisation"] == pytest.approx(900.0)
    assert g["missed"] == pytest.approx(200.0**2 / 2)
    assert g["false"] == pytest.approx(2 * 200.0**2 / 2)
    assert g["gospa"] == pytest.approx((900.0 + 3 * 20000.0) ** 0.5)
    assert g["assignment"].tolist() == [0, -1]


def test_track_metrics_counts_switches_fragments_continuity():
    """One truth over 8 scans, estimates by hand: ids 7 7 _ 7 9 9 _ 9 (``_``: no estimate near it): one switch
    (7 -> 9), two fragmentations (the resumptions at scans 3 and 7), longest run 2 of 8 present scans."""
    ids = [7, 7, None, 7, 9, 9, None, 9]
    truth_ids, truth_pos, est_ids, est_pos = [], [], [], []
    for s, e in enumerate(ids):
        x = np.array([[100.0 * s, 0.0, 0.0]])
        truth_ids.append(np.array([1]))
        truth_pos.append(x)
        if e is None:
            est_ids.append(np.array([3]))
            est_pos.append(x + 5000.0)  # a false track far away
        else:
            est_ids.append(np.array([e]))
            est_pos.append(x + 10.0)
    out = track_metrics(truth_ids, truth_pos, est_ids, est_pos, c=200.0)
    assert out["id_switches"] == 1
    assert out["fragmentations"] == 2
    assert out["continuity"] == pytest.approx(2 / 8)
    assert out["coverage"] == pytest.approx(6 / 8)
    expected = [gospa(t, e)["gospa"] for t, e in zip(truth_pos, est_pos)]
    assert out["gospa"] == pytest.approx(np.mean(expected))
    with pytest.raises(ValueError, match="one entry per scan"):
        track_metrics(truth_ids, truth_pos[:-1], est_ids, est_pos)


# --- the per-track filter ------------------------------------------------------------------------------------------

from immnet.filters.multi import (  # noqa: E402
    Cover, IMMFilter, MultiTargetTracker, TrackFilter, TrackScore, TwoPointStart, assign, gate_pairs,
    jpda_probabilities,
)


def _method_track(name: str, z: np.ndarray, dt: float, r: float, robust: float | None = None) -> np.ndarray:
    """Method ``name``'s own ``track`` of ``z [B, T, 3]`` at interval ``dt``, told ``r`` (and Huber's ``robust``)."""
    import torch
    from tensordict import TensorDict

    from immnet import keys
    from immnet.filters.methods import build_method
    from immnet.imm.measurement import Isotropic

    method = build_method(name)
    method.measurement, method.needs, method.robust = Isotropic(r), (), robust
    B = z.shape[0]
    batch = TensorDict({keys.MEASUREMENTS: torch.tensor(z), keys.DT: torch.full((B,), dt, dtype=torch.float64)},
                       batch_size=[B])
    return method.track(batch)[keys.STATE].numpy()


def _filter_track(f, z: np.ndarray, dt: float, r: float) -> np.ndarray:
    """The batched filter ``f`` started at the first plot and stepped with predict/update over ``z [B, T, 3]``."""
    R = np.broadcast_to(r * r * np.eye(3), (z.shape[0], 3, 3))
    f.start(z[:, 0], R)
    out = [f.state()[0]]
    for k in range(1, z.shape[1]):
        f.predict(dt)
        f.update(z[:, k], R)
        out.append(f.state()[0])
    return np.stack(out, 1)


@pytest.mark.parametrize("name", ["real-imm-singer", "real-imm"])
def test_two_point_start_with_a_vertical_speed_prior_is_the_bayes_posterior(name):
    """A pair's start fused with the prior ``vz ~ N(0, s^2)`` (``vz_std``) is the Gaussian posterior in information
    form, computed apart in float64: ``P = (P0^-1 + e e^T / s^2)^-1``, ``x = P P0^-1 x0``, from the pair's start
    without the prior (``x0``, ``P0``); per-axis and joint modes alike. A huge ``s`` leaves the start as it was."""
    rng = np.random.default_rng(3)
    k, dt, s = 4, 5.0, 5.0
    z_prev = rng.uniform(-40e3, 40e3, (k, 3))
    z = z_prev + rng.normal(0, 200.0, (k, 3)) * dt
    R = np.stack([np.diag(v) for v in rng.uniform(30.0, 150.0, (k, 3)) ** 2])
    Rp = np.stack([np.diag(v) for v in rng.uniform(30.0, 150.0, (k, 3)) ** 2])
    states = {}
    for prior in (None, s, 1e9):
        f = TrackFilter.from_method(name)
        f.start(z, R, z_prev, Rp, np.full(k, dt), prior)
        states[prior] = f.state()
    x0, P0 = states[None]
    e = np.zeros(9)
    e[7] = 1.0
    for i in range(k):
        info = np.linalg.inv(P0[i])
        P = np.linalg.inv(info + np.outer(e, e) / s**2)
        np.testing.assert_allclose(states[s][1][i], P, rtol=1e-7, atol=1e-9 * np.abs(P).max())
        np.testing.assert_allclose(states[s][0][i], P @ info @ x0[i], rtol=1e-7, atol=1e-6)
    assert np.abs(states[s][0][:, 7]).max() < np.abs(x0[:, 7]).max()
    np.testing.assert_allclose(states[1e9][0], x0, atol=1e-6)
    # the tracker starts its tracks with its initiation's prior
    tracker = MultiTargetTracker(name, init=TwoPointStart(vz_std=s))
    tracker.step(0.0, z_prev[:1], Rp[:1])
    tracker.step(dt, z[:1], R[:1])
    (track,) = tracker.tracks()
    np.testing.assert_allclose(track.state, states[s][0][0], rtol=1e-9, atol=1e-6)


@pytest.mark.parametrize("name, want", [("real-imm", [0.9, 0.1 / 3, 0.1 / 3, 0.1 / 3]),  # cv, ca, ct+2, ct-2
                                        ("real-imm-singer", [0.9, 0.05, 0.05]),  # cv, ca, singer (on every axis)
                                        ("real-ca", [1.0])])  # one model: a Kalman filter
def test_a_new_track_starts_likely_straight(name, want):
    """``TwoPointStart(p_cv=0.9)`` (the default): a new track's first mode probabilities are 0.9 on the
    constant-velocity model and the rest spread evenly over the others, on every axis of a per-axis IMM; ``p_cv=None``
    gives the filter's own (uniform); a filter of one model keeps its one mode."""
    z0, z1 = np.array([[1000.0, 2000.0, 8000.0]]), np.array([[2000.0, 2500.0, 8010.0]])
    R = np.eye(3)[None] * 900.0
    for p_cv, expected in ((0.9, want), (None, [1.0 / len(want)] * len(want))):
        tracker = MultiTargetTracker(name, init=TwoPointStart(p_cv=p_cv))
        tracker.step(0.0, z0, R)
        tracker.step(5.0, z1, R)
        mu = tracker.filter.mu.numpy()
        assert mu.shape[0] == 1
        np.testing.assert_allclose(mu[0], np.broadcast_to(expected, mu[0].shape), rtol=0, atol=1e-15)


@pytest.mark.parametrize("name", ["real-imm-singer", "real-imm", "real-ca"])
def test_filter_is_the_single_target_method(name):
    """The batched filter of a method (per-axis IMM, joint IMM, Kalman filter), started at the first plot and stepped
    with predict/update (a NaN row: missed), filters what the method's own ``track`` filters."""
    rng = np.random.default_rng(1)
    B, T, dt, r = 3, 25, 2.0, 40.0
    z = np.cumsum(rng.normal(0, 60.0 * dt, (B, T, 3)), 1) + rng.normal(0, r, (B, T, 3))
    z[0, 5] = np.nan
    np.testing.assert_allclose(_filter_track(TrackFilter.from_method(name, r=r), z, dt, r), _method_track(name, z, dt, r),
                               rtol=1e-9, atol=1e-6)


@pytest.mark.parametrize("name", ["real-imm-singer", "real-imm"])
def test_a_robust_methods_filter_updates_as_its_track(name):
    """A method's robust update (Huber's ``k``) is its multi-target filter's too: with outliers among a track's plots
    the batched filter filters what the robust method's own ``track`` filters (and not what the plain one does); a
    configured robust method brings its ``k`` (radar-imm-robust-5s's, as its YAML says)."""
    from immnet.filters.methods import build_method

    k_config = build_method("radar-imm-robust-5s").robust
    assert k_config is not None and TrackFilter.from_method("radar-imm-robust-5s").robust == k_config
    rng = np.random.default_rng(4)
    B, T, dt, r, k = 3, 25, 2.0, 40.0, 2.0
    z = np.cumsum(rng.normal(0, 60.0 * dt, (B, T, 3)), 1) + rng.normal(0, r, (B, T, 3))
    z[:, 9] += 15 * r  # an outlier on every track
    robust, plain = _method_track(name, z, dt, r, k), _method_track(name, z, dt, r)
    f = TrackFilter.from_method(name, r=r)
    f.robust = k
    np.testing.assert_allclose(_filter_track(f, z, dt, r), robust, rtol=1e-9, atol=1e-6)
    assert np.abs(robust - plain)[:, 9:, 0::3].max() > 50.0  # the outlier moves the plain filter's track


def test_mixture_update_with_certain_association_is_the_update():
    """``update_mixture`` with all the probability on one plot (or on none) is ``update`` with that plot (or NaN)."""
    rng = np.random.default_rng(2)
    K, r = 4, 30.0
    R = np.broadcast_to(r * r * np.eye(3), (K, 3, 3)).copy()
    fa, fb = TrackFilter.from_method("real-imm-singer", r=r), TrackFilter.from_method("real-imm-singer", r=r)
    z0, z1 = rng.normal(0, 1000, (K, 3)), rng.normal(0, 1000, (K, 3))
    for f in (fa, fb):
        f.start(z1, R, z0, R, np.full(K, 2.0))
        f.predict(2.0)
    x_prior = fa.state()[0]
    plots = x_prior[:, None, 0::3] + rng.normal(0, 50, (K, 2, 3))
    z = plots[:, 0].copy()
    z[3] = np.nan  # track 3: no plot
    fa.update(z, R)
    # every track's two plots as pairs: the first with probability 1 (tracks 0-2), none with probability 1 (track 3)
    track = np.repeat(np.arange(K), 2)
    beta = np.tile([1.0, 0.0], K)
    beta[6] = 0.0
    fb.update_mixture(track, plots.reshape(-1, 3), np.repeat(R, 2, 0), beta, np.array([0.0, 0.0, 0.0, 1.0]))
    for a, b in zip(fa.state(), fb.state()):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-8)
    np.testing.assert_allclose(fa.mode_probs(), fb.mode_probs(), atol=1e-12)


# --- gating and association against brute force --------------------------------------------------------------------

def test_gate_pairs_is_the_full_chi_square_test():
    """The k-d tree's candidates lose no pair: the gated pairs and their log-likelihoods are those of testing every
    track against every plot (numpy's inverse, scipy's Gaussian density)."""
    from scipy.stats import chi2, multivariate_normal

    rng = np.random.default_rng(3)
    K, N = 30, 400
    z_pred = rng.uniform(0, 5000, (K, 3))
    A = rng.normal(0, 1, (K, 3, 3)) * rng.uniform(20, 200, (K, 1, 1))
    S = A @ A.transpose(0, 2, 1) + 10 * np.eye(3)
    plots = rng.uniform(0, 5000, (N, 3))
    plots[:K] = z_pred + rng.normal(0, 100, (K, 3))
    Bm = rng.normal(0, 1, (N, 3, 3)) * rng.uniform(5, 60, (N, 1, 1))
    R = Bm @ Bm.transpose(0, 2, 1) + np.eye(3)
    thr = chi2.ppf(0.999, 3)
    ti, pj, ll = gate_pairs(z_pred, S, plots, R, thr)
    want = {}
    for i in range(K):
        for j in range(N):
            C = S[i] + R[j]
            nu = plots[j] - z_pred[i]
            if nu @ np.linalg.inv(C) @ nu <= thr:
                want[(i, j)] = multivariate_normal(z_pred[i], C).logpdf(plots[j])
    got = {(int(i), int(j)): v for i, j, v in zip(ti, pj, ll)}
    assert set(got) == set(want) and len(want) >= K
    for key, v in want.items():
        assert got[key] == pytest.approx(v, rel=1e-9, abs=1e-9)


def test_assign_is_the_best_assignment_by_brute_force():
    """Per random gated-pair pattern: the clustered assignment has the most pairs and, among those, the least cost,
    found by enumerating every matching."""
    import itertools

    rng = np.random.default_rng(4)
    for _ in range(60):
        K, N = int(rng.integers(1, 5)), int(rng.integers(1, 5))
        mask = rng.random((K, N)) < 0.5
        ti, pj = np.nonzero(mask)
        cost = rng.normal(0, 5, len(ti))
        c = {(i, j): v for i, j, v in zip(ti, pj, cost)}
        best = (0, 0.0)
        for perm in itertools.permutations(range(max(K, N)), K):
            pairs = [(i, j) for i, j in enumerate(perm) if j < N and (i, j) in c]
            key = (len(pairs), sum(c[p] for p in pairs))
            if key[0] > best[0] or (key[0] == best[0] and key[1] < best[1] - 1e-12):
                best = key
        chosen = assign(ti, pj, cost)
        assert len(set(ti[chosen])) == len(chosen) == len(set(pj[chosen]))
        assert len(chosen) == best[0]
        assert cost[chosen].sum() == pytest.approx(best[1], abs=1e-9)


def _jpda_brute(ti, pj, ll, K, pd, pg, lam):
    """Every joint event by recursion over tracks, weights multiplied out as written."""
    opts = {i: [(k, j) for k, (t, j) in enumerate(zip(ti, pj)) if t == i] for i in range(K)}
    beta, beta0, total = np.zeros(len(ti)), np.zeros(K), 0.0
    events = []

    def rec(i, used, chosen, w):
        if i == K:
            events.append((list(chosen), w))
            return
        rec(i + 1, used, chosen + [None], w * (1 - pd * pg))
        for k, j in opts[i]:
            if j not in used:
                rec(i + 1, used | {j}, chosen + [k], w * pd * np.exp(ll[k]) / lam)

    rec(0, frozenset(), [], 1.0)
    for chosen, w in events:
        total += w
        for i, k in enumerate(chosen):
            if k is None:
                beta0[i] += w
            else:
                beta[k] += w
    return beta / total, beta0 / total


def test_jpda_probabilities_by_brute_force():
    """Exact JPDA: each cluster's probabilities are those of enumerating the whole scene's joint events (clusters
    are independent); one track with two plots: ``beta_j = L_j / (1 - pd pg + L_1 + L_2)``."""
    rng = np.random.default_rng(5)
    pd, pg, lam = 0.9, 0.999, 1e-9
    for _ in range(30):
        K, N = int(rng.integers(1, 5)), int(rng.integers(1, 6))
        ti, pj = np.nonzero(rng.random((K, N)) < 0.5)
        ll = rng.uniform(-25, -15, len(ti))
        beta, beta0 = jpda_probabilities(ti, pj, ll, K, pd, pg, lam)
        want, want0 = _jpda_brute(ti, pj, ll, K, pd, pg, lam)
        np.testing.assert_allclose(beta, want, atol=1e-12)
        np.testing.assert_allclose(beta0, want0, atol=1e-12)
    ll = np.array([-18.0, -20.0])
    beta, beta0 = jpda_probabilities(np.array([0, 0]), np.array([0, 1]), ll, 1, pd, pg, lam)
    L = pd * np.exp(ll) / lam
    np.testing.assert_allclose(beta, L / (1 - pd * pg + L.sum()), rtol=1e-12)
    cheap, cheap0 = jpda_probabilities(ti, pj, rng.uniform(-25, -15, len(ti)), K, pd, pg, lam, max_events=1)
    assert (cheap >= 0).all() and (cheap0 > 0).all()
    assert np.allclose(np.bincount(ti, cheap, K) + cheap0, 1.0)


# --- hand-made scenes ----------------------------------------------------------------------------------------------

BOX = np.array([[-20e3, 20e3], [-20e3, 20e3], [0.0, 10e3]])


def _scene(rng, starts, vels, T, dt, r, pd=1.0, clutter=0.0, box=BOX):
    """Straight flights ``start + v t``; per scan the detected truths' plots (noise ``r``, each detected with ``pd``)
    and Poisson(``clutter``) false plots uniform in ``box``, shuffled. Yields ``(t, truth [n, 3], plots, is_true)``."""
    starts, vels = np.asarray(starts, float), np.asarray(vels, float)
    for k in range(T):
        t = k * dt
        truth = starts + vels * t
        det = rng.random(len(truth)) < pd
        true_plots = truth[det] + rng.normal(0, r, (int(det.sum()), 3))
        false_plots = rng.uniform(box[:, 0], box[:, 1], (rng.poisson(clutter), 3))
        plots = np.concatenate([true_plots, false_plots])
        is_true = np.full(len(plots), -1)
        is_true[:len(true_plots)] = np.flatnonzero(det)
        order = rng.permutation(len(plots))
        yield t, truth, plots[order], is_true[order]


def _run(tracker, scenes):
    """Step through a scene; the metrics' per-scan lists (confirmed tracks as estimates)."""
    lists = ([], [], [], [])
    for t, truth, plots, _ in scenes:
        reps = tracker.step(t, plots)
        for v, a in zip(lists, (np.arange(len(truth)), truth, [p.track_id for p in reps],
                                np.array([p.state[0::3] for p in reps]).reshape(-1, 3))):
            v.append(np.asarray(a))
    return lists


# the hand-made scenes run with a model-based IMM at 1-2 s scans and with a shipped network at the 5 s scans it was
# trained for (immnet.tracking.network_filter; GNN: a network refuses JPDA)
FILTERS = [("real-imm-singer", 1.0), ("radar-5s", 5.0)]


@pytest.mark.parametrize("associator,filt,dt", [("gnn", "real-imm-singer", 2.0), ("jpda", "real-imm-singer", 2.0),
                                               ("gnn", "radar-5s", 5.0)])
def test_crossing_targets_keep_their_ids(associator, filt, dt):
    """Two flights crossing at 30 degrees over the same point at the same scan, 300 m (1000 ft, the least vertical
    separation of two aircraft under instrument flight rules) apart in height: after the crossing each is still
    followed by the track that followed it before (no id switch), by two different tracks, without a break. (At the
    same point, no separation, every filter swapped the two in 25-60 % of 20 seeds, the IMMs at 2 s and 5 s included:
    plots 30 m apart at one scan say nothing of which aircraft is which; 100 m and 300 m: none of 20.)"""
    rng = np.random.default_rng(10)
    v = 200.0
    a = np.deg2rad(15.0)
    vels = [[v * np.cos(a), v * np.sin(a), 0.0], [v * np.cos(a), -v * np.sin(a), 0.0]]
    T = 40
    starts = [[-np.array(w[0]) * 20 * dt, -np.array(w[1]) * 20 * dt, 5000.0 + 300.0 * i]  # over one point at scan 20
              for i, w in enumerate(vels)]
    tracker = MultiTargetTracker(filt, r=30.0, associator=associator)
    ti, tp, ei, ep = _run(tracker, _scene(rng, starts, vels, T, dt, 30.0))
    out = track_metrics(ti, tp, ei, ep, c=200.0)
    assert out["id_switches"] == 0 and out["fragmentations"] == 0
    ids = {truth: {int(e[g["assignment"][k]]) for e, g in zip(ei, out["per_scan"]) if g["assignment"][k] >= 0}
           for k, truth in enumerate([0, 1])}
    assert all(len(s) == 1 for s in ids.values()) and ids[0] != ids[1]
    # confirmed on the third plot (no clutter: the track score), followed throughout since
    first = next(k for k, e in enumerate(ei) if len(e))
    assert first == 2 and all(r["assigned"] == T - first for r in out["per_truth"].values())


@pytest.mark.parametrize("dt,chosen", [(1.0, "real-imm"), (3.0, "real-imm"), (5.2, "mtt-imm-5s"), (6.0, "mtt-imm-5s"),
                                       (7.0, "real-imm-11s"), (11.5, "real-imm-11s")])
def test_default_filter_is_the_imm_tuned_at_the_scan_interval(dt, chosen):
    """The default per-track filter (``real-imm-by-interval``) chooses, at the second scan, the IMM of the band that
    holds the scan interval (``MULTI_TARGET_BANDS``: up to 3 s, up to 6 s, beyond), and the tracker then reports, to
    the bit, what it reports built with that method by name; before its second scan it holds no filter."""
    from immnet.filters.registry import MULTI_TARGET_BANDS, MULTI_TARGET_FILTER

    assert [name for _, name in MULTI_TARGET_BANDS] == ["real-imm", "mtt-imm-5s", "real-imm-11s"]
    scans = list(_scene(np.random.default_rng(3), [[-5e3, 0.0, 5e3], [5e3, 2e3, 6e3]],
                        [[150.0, 20.0, 0.0], [-120.0, 60.0, 2.0]], 12, dt, 30.0, pd=0.9, clutter=2.0))
    default, named = MultiTargetTracker(r=30.0), MultiTargetTracker(chosen, r=30.0)
    assert default.filter.name == MULTI_TARGET_FILTER and default.filter.chosen is None
    for k, (t, _, plots, _) in enumerate(scans):
        a, b = default.step(t, plots), named.step(t, plots)
        assert default.filter.chosen == (None if k == 0 else chosen)
        assert [r.track_id for r in a] == [r.track_id for r in b]
        assert all(np.array_equal(x.state, y.state) and np.array_equal(x.cov, y.cov) for x, y in zip(a, b))
    assert len(named.tracks()) == len(default.tracks()) >= 2


def test_the_default_filter_is_no_single_target_method():
    """Named where a method of labelled tracks is asked for, the multi-target default is refused in one line that says
    what it is and names its IMMs."""
    from immnet.filters.methods import build_method

    with pytest.raises(ValueError, match=r"^real-imm-by-interval is the multi-target tracker's per-track filter .*"
                                         r"\(real-imm, mtt-imm-5s, real-imm-11s\)$"):
        build_method("real-imm-by-interval")


@pytest.mark.parametrize("filt,dt", FILTERS)
def test_plot_outside_every_gate_starts_a_tentative_track(filt, dt):
    """A confirmed track; a plot far outside its gate is kept as a seed, and the next scan's plot within the
    velocity gate of it starts a tentative track of a new id at that plot, with the velocity the two plots give
    (the IMM's two-point start; a network's start is its own, within a few noise stds of it)."""
    r = 20.0
    tracker = MultiTargetTracker(filt, r=r, init=TwoPointStart(vz_std=None))  # the pair alone (no prior)
    far0 = np.array([15000.0, 15000.0, 8000.0])
    far1 = far0 + np.array([-150.0, 100.0, 5.0]) * dt
    for k in range(4):
        plots = [[200.0 * k * dt, 0.0, 3000.0]]
        if k == 2:
            plots.append(far0)
        if k == 3:
            plots.append(far1)
        reps = tracker.step(k * dt, np.array(plots))
        if k == 2:
            assert len(tracker.tracks()) == 1 and len(tracker.seed_z) == 1  # a seed, not yet a track
    (old,) = reps
    assert old.confirmed and old.updated
    new = [t for t in tracker.tracks() if t.track_id != old.track_id]
    assert len(new) == 1 and not new[0].confirmed and new[0].updated and new[0].track_id > old.track_id
    exact = filt == "real-imm-singer"
    np.testing.assert_allclose(new[0].state[0::3], far1, atol=1e-9 if exact else 3 * r)
    np.testing.assert_allclose(new[0].state[1::3], (far1 - far0) / dt, atol=1e-9 if exact else 3 * r / dt)
    # a plot too far for max_speed (500 m/s: beyond 300 m/s and 3 standard deviations of the two plots' noise)
    # pairs with nothing
    tracker2 = MultiTargetTracker(filt, r=r, init=type(tracker.init)(max_speed=300.0))
    tracker2.step(0.0, far0[None])
    tracker2.step(dt, (far0 + [500.0 * dt, 0.0, 0.0])[None])
    assert tracker2.tracks() == [] and len(tracker2.seed_z) == 2


@pytest.mark.parametrize("filt,dt", FILTERS)
def test_unconfirmed_track_is_dropped_after_its_window(filt, dt):
    """3 of 4: a pair of plots (scans 0, 1) starts a tentative track; with nothing more it lives through scan 2 (it
    may still get its third hit at scan 3) and is dropped at scan 3; it is never confirmed."""
    tracker = MultiTargetTracker(filt, r=20.0, confirm=(3, 4))
    p = np.array([1000.0, 2000.0, 3000.0])
    tracker.step(0.0, p[None])
    tracker.step(dt, (p + [100.0 * dt, 0, 0])[None])
    (tent,) = tracker.tracks()
    assert not tent.confirmed
    assert tracker.step(2 * dt, np.zeros((0, 3))) == []
    assert [t.track_id for t in tracker.tracks()] == [tent.track_id]
    tracker.step(3 * dt, np.zeros((0, 3)))
    assert tracker.tracks() == [] and len(tracker.filter) == 0
    # the same start with its third plot at scan 3 confirms
    tracker = MultiTargetTracker(filt, r=20.0, confirm=(3, 4))
    for k in (0, 1):
        tracker.step(k * dt, (p + [100.0 * k * dt, 0, 0])[None])
    tracker.step(2 * dt, np.zeros((0, 3)))
    (conf,) = tracker.step(3 * dt, (p + [300.0 * dt, 0, 0])[None])
    assert conf.confirmed and conf.track_id == tent.track_id


@pytest.mark.parametrize("filt,dt", [("real-imm-singer", 2.0), ("radar-5s", 5.0)])
def test_missed_scan_coasts_then_deletes(filt, dt):
    """A confirmed track missed at a scan keeps its id, is not updated and stands at its prediction (the last
    position plus the velocity times the interval); detected again it is updated under the same id; after
    ``delete_after`` consecutive misses it is gone."""
    tracker = MultiTargetTracker(filt, r=10.0, delete_after=3)
    v = np.array([150.0, -80.0, 2.0])
    p0 = np.array([0.0, 0.0, 4000.0])
    for k in range(6):
        reps = tracker.step(k * dt, (p0 + v * k * dt)[None])
    (rep,) = reps
    (coast,) = tracker.step(6 * dt, np.zeros((0, 3)))
    assert coast.track_id == rep.track_id and coast.confirmed and not coast.updated
    np.testing.assert_allclose(coast.state[0::3], rep.state[0::3] + rep.state[1::3] * dt, atol=1.0)
    assert np.trace(coast.cov[0::3, 0::3]) > np.trace(rep.cov[0::3, 0::3])
    (back,) = tracker.step(7 * dt, (p0 + v * 7 * dt)[None])
    assert back.track_id == rep.track_id and back.updated
    for k in (8, 9):
        assert [t.track_id for t in tracker.step(k * dt, np.zeros((0, 3)))] == [rep.track_id]
    assert tracker.step(10 * dt, np.zeros((0, 3))) == [] and tracker.tracks() == []


def test_misses_delete_a_track_once_they_span_min_coast_seconds():
    """At 1 s scans, ``delete_after=3`` misses span 3 s: with ``min_coast`` 4 s (the default) the track outlives its
    third miss and is deleted at its fourth (4 s after its last plot); with ``min_coast=0`` at its third. At 2 s scans
    three misses span 6 s and the default deletes at the third, as ``delete_after`` says."""
    v, p0 = np.array([150.0, -80.0, 2.0]), np.array([0.0, 0.0, 4000.0])
    for dt, min_coast, gone_at in ((1.0, None, 4), (1.0, 0.0, 3), (2.0, None, 3)):
        kw = {} if min_coast is None else {"min_coast": min_coast}
        tracker = MultiTargetTracker("real-imm-singer", r=10.0, delete_after=3, **kw)
        for k in range(6):
            reps = tracker.step(k * dt, (p0 + v * k * dt)[None])
        (rep,) = reps
        for miss in range(1, 6):
            ids = [t.track_id for t in tracker.step((5 + miss) * dt, np.zeros((0, 3)))]
            assert ids == ([] if miss >= gone_at else [rep.track_id]), (dt, min_coast, miss)
    with pytest.raises(ValueError, match=r"min_coast must be a finite number of seconds >= 0, got -1.0"):
        MultiTargetTracker("real-imm-singer", min_coast=-1.0)


@pytest.mark.parametrize("associator", ["gnn", "jpda"])
def test_track_leaving_the_cover_is_deleted_at_its_first_miss_outside(associator):
    """A radar with a cover of 20 km: an aircraft flying outward at 200 m/s is plotted every 2 s while its range
    is at most 20 km. Told the cover, the tracker deletes its track at the first scan without a plot where the
    estimate lies beyond 20 km (at the scan it leaves, not ``delete_after`` scans later); a miss inside the cover
    coasts as before. Not told it, the track coasts its ``delete_after`` scans outside. The range is computed by
    hand."""
    v, dt = np.array([200.0, 0.0, 0.0]), 2.0
    p0 = np.array([12000.0, 0.0, 3000.0])
    reported = {}
    for cover in (None, Cover(20000.0)):
        tracker = MultiTargetTracker("real-imm-singer", r=20.0, delete_after=3, associator=associator, cover=cover)
        rows = []
        for k in range(24):
            p = p0 + v * k * dt
            inside = np.sqrt(p @ p) <= 20000.0
            plots = p[None] if inside and k != 8 else np.zeros((0, 3))  # scan 8: a miss inside the cover
            rows.append([(r.track_id, r.updated) for r in tracker.step(k * dt, plots)])
        reported[cover is None] = rows
    last_in = max(k for k in range(24) if np.linalg.norm(p0 + v * k * dt) <= 20000.0)
    told, blind = reported[False], reported[True]
    (tid, _), = told[3]
    assert told[8] == [(tid, False)] == blind[8]  # a miss inside the cover coasts, told the cover or not
    assert told[last_in] == [(tid, True)] and all(r == [] for r in told[last_in + 1:])
    assert [len(r) for r in blind[last_in + 1:last_in + 3]] == [1, 1] and blind[last_in + 3] == []
    with pytest.raises(ValueError, match="a cover needs 0 < max_range < inf"):
        Cover(0.0)
    with pytest.raises(TypeError, match="cover must be a Cover or None"):
        MultiTargetTracker("real-imm-singer", cover=20000.0)


@pytest.mark.parametrize("associator,filt", [("gnn", "real-imm-singer"), ("jpda", "real-imm-singer"),
                                             ("gnn", "radar-5s")])
def test_clutter_alone_confirms_no_track(associator, filt):
    """40 scans of 20 false plots each (uniform over 40 x 40 x 10 km, 1.25e-12 per m^3) at 5 s: pairs within the
    speed gate start tentative tracks, and none of them is confirmed."""
    rng = np.random.default_rng(11)
    tracker = MultiTargetTracker(filt, r=50.0, associator=associator, clutter_density=1.25e-12)
    started = 0
    for t, _, plots, _ in _scene(rng, np.zeros((0, 3)), np.zeros((0, 3)), 40, 5.0, 50.0, clutter=20.0):
        assert tracker.step(t, plots) == []
        started = max(started, tracker._next_id - 1)
    assert started >= 3  # initiation ran: tentative tracks were started and dropped


def test_track_score_adds_the_log_likelihood_ratio():
    """A TrackScore's score by hand: a pair starts at ``log(pd / (beta_fa V))`` (``V`` the start's ball), a miss adds
    ``log(1 - pd pg)``, a plot ``log(pd N(nu; 0, S + R) / beta_fa)`` (the gate's log-likelihood); ``beta_fa`` is the
    plots per scan no confirmed track took over the cover's volume, without a cover over the half ball out to the
    farthest plot so far, before any plot the tracker's ``clutter_density``; ``start=False`` starts at 0."""
    import copy

    r, dt, pd, lam = 20.0, 5.0, 0.9, 1e-12
    p = np.array([1000.0, 2000.0, 3000.0])
    v = np.array([100.0, 0.0, 0.0])
    tracker = MultiTargetTracker("real-imm-singer", r=r, pd=pd, clutter_density=lam,
                                 confirm=TrackScore(alpha=1e-30, beta=1e-30))  # neither confirmed nor dropped
    assert tracker.clutter_density_now() == lam  # no plot yet
    for k in (0, 1):
        tracker.step(k * dt, (p + v * k * dt)[None])
    reach = np.linalg.norm(p + v * dt)  # the farther of the two plots; one plot a scan, none taken
    lam = 1.0 / (2 * np.pi / 3 * reach**3)
    assert tracker.clutter_density_now() == pytest.approx(lam, rel=1e-12)
    radius = tracker.init.max_speed * dt + tracker.init.sigma * np.sqrt(6 * r**2)
    start = np.log(pd / (lam * 4 / 3 * np.pi * radius**3))
    np.testing.assert_allclose(tracker.score, [start], rtol=1e-12)
    tracker.step(2 * dt, np.zeros((0, 3)))
    np.testing.assert_allclose(tracker.score, [start + np.log1p(-pd * tracker.pg)], rtol=1e-12)
    probe = copy.deepcopy(tracker.filter)  # the next scan's gate, the tracker's filter untouched
    z_pred, S = probe.predict(dt)
    before = tracker.score.copy()
    plot = p + v * 3 * dt + [30.0, -20.0, 10.0]
    _, _, ll = gate_pairs(z_pred, S, plot[None], r**2 * np.eye(3)[None], tracker.threshold)
    tracker.step(3 * dt, plot[None])
    # the reach grown to the new plot; the plots a scan (1, 1, 0, 1) averaged with weight 0.1: 0.9 * 0.9 + 0.1
    lam = 0.91 / (2 * np.pi / 3 * np.linalg.norm(plot) ** 3)
    np.testing.assert_allclose(tracker.score, before + np.log(pd) + ll - np.log(lam), rtol=1e-12)
    # told a cover: the density is the plots per scan over its volume (one plot a scan here, none taken by a
    # confirmed track), the first scan's count alone, then the exponential average
    cover = Cover(20000.0)
    told = MultiTargetTracker("real-imm-singer", r=r, pd=pd, cover=cover, confirm=TrackScore(alpha=1e-30,
                                                                                             smoothing=0.5))
    told.step(0.0, np.stack([p, -p]))
    assert told.clutter_per_scan == 2.0
    told.step(dt, (p + v * dt)[None])
    assert told.clutter_per_scan == 1.5 and told.clutter_density_now() == pytest.approx(1.5 / cover.volume)
    plain = MultiTargetTracker("real-imm-singer", r=r, confirm=TrackScore(start=False))
    for k in (0, 1):
        plain.step(k * dt, (p + v * k * dt)[None])
    assert plain.score.tolist() == [0.0]


@pytest.mark.parametrize("clutter,confirmed_at", [(2.0, 2), (20.0, 3)])
def test_track_score_confirms_a_target_not_clutter(clutter, confirmed_at):
    """One flight among ``clutter`` false plots a scan (uniform over 40 x 40 x 10 km) at 5 s, told a cover of 30 km
    and no clutter density: the score confirms one track, on the flight, and none on the clutter, estimating the
    clutter plots per scan within 25 %; with little clutter on the flight's third plot (scan 2), with more on its
    fourth (scan 3), where (4, 5) confirms it either way."""
    first = {}
    for confirm in (TrackScore(), (4, 5)):
        rng = np.random.default_rng(14)
        tracker = MultiTargetTracker("real-imm-singer", r=50.0, cover=Cover(30000.0), confirm=confirm)
        ti, tp, ei, ep = _run(tracker, _scene(rng, [[-15000.0, -5000.0, 6000.0]], [[120.0, 40.0, 0.0]], 40, 5.0,
                                              50.0, clutter=clutter))
        out = track_metrics(ti, tp, ei, ep, c=200.0)
        assert len({int(i) for e in ei for i in e}) == 1 and out["per_truth"][0]["assigned"] == 40 - len(
            [e for e in ei if not len(e)])
        first[str(confirm)] = next(s for s, e in enumerate(ei) if len(e))
        if isinstance(confirm, TrackScore):
            assert tracker.clutter_per_scan == pytest.approx(clutter, rel=0.25)
    assert first == {str(TrackScore()): confirmed_at, "(4, 5)": 3}


def test_track_score_settings_and_cover_volume():
    """A TrackScore is recorded as its fields (``(M, N)`` as ``[M, N]``) and printed with the tracker; a cover's volume
    is the ball above its lowest elevation; a TrackScore's thresholds are Wald's."""
    assert repr(MultiTargetTracker(r=30.0)) == ("MultiTargetTracker(ByInterval(not chosen yet), GNN, confirm "
                                                f"{TrackScore()!r}; 0 confirmed of 0 tracks)")
    assert repr(MultiTargetTracker("real-imm-singer", associator="jpda", confirm=(4, 5))).startswith(
        "MultiTargetTracker(IMMFilter(real-imm-singer")
    assert MultiTargetTracker("real-imm-singer", confirm=(4, 5)).settings()["confirm"] == [4, 5]
    assert MultiTargetTracker("real-imm-singer").settings()["confirm"] == asdict(TrackScore())  # the default
    rec = MultiTargetTracker("real-imm-singer", confirm=TrackScore(alpha=1e-5)).settings()["confirm"]
    assert rec == {"alpha": 1e-5, "beta": 0.5, "max_scans": 8, "smoothing": 0.1, "start": True, "seed_scans": 2}
    assert Cover(1000.0).volume == pytest.approx(2 * np.pi / 3 * 1e9)
    assert Cover(1000.0, 30.0).volume == pytest.approx(np.pi / 3 * 1e9)
    rule = TrackScore(alpha=1e-4, beta=0.1)
    assert rule.confirm_at == pytest.approx(np.log(0.9 / 1e-4)) and rule.drop_at == pytest.approx(np.log(0.1 / 0.9999))
    for kwargs, msg in (({"alpha": 0.0}, r"TrackScore.alpha is a probability in \(0, 1\), got 0.0"),
                        ({"beta": 1.0}, r"TrackScore.beta is a probability in \(0, 1\), got 1.0"),
                        ({"alpha": 0.6, "beta": 0.5}, "TrackScore needs alpha \\+ beta < 1"),
                        ({"max_scans": 1}, "TrackScore.max_scans must be a whole number of scans >= 2, got 1"),
                        ({"seed_scans": 1.5}, "TrackScore.seed_scans must be a whole number of scans >= 1, got 1.5"),
                        ({"smoothing": 0.0}, r"TrackScore.smoothing is a weight in \(0, 1\], got 0.0")):
        with pytest.raises(ValueError, match=msg):
            TrackScore(**kwargs)


@pytest.mark.parametrize("filt,dt", [("real-imm-singer", 2.0), ("radar-5s", 5.0)])
def test_one_target_at_pd_09_keeps_one_id(filt, dt):
    """One flight, detected with probability 0.9, among 5 false plots a scan, 120 scans: one confirmed track follows
    it from its confirmation to the end, and no other track is ever confirmed."""
    rng = np.random.default_rng(12)
    tracker = MultiTargetTracker(filt, r=50.0)
    ti, tp, ei, ep = _run(tracker, _scene(rng, [[-15000.0, -5000.0, 6000.0]], [[120.0, 40.0, 0.0]], 120, dt, 50.0,
                                           pd=0.9, clutter=5.0))
    out = track_metrics(ti, tp, ei, ep, c=200.0)
    ids = {int(i) for e in ei for i in e}
    assert len(ids) == 1 and out["id_switches"] == 0 and out["fragmentations"] == 0
    first = next(s for s, e in enumerate(ei) if len(e))
    assert first <= 6 and out["per_truth"][0]["assigned"] == 120 - first


def test_monte_carlo_error_is_the_imm_told_the_association():
    """Three flights, detected with probability 0.95, among 10 false plots a scan (10 runs of 40 scans at 2 s): the
    tracker's mean position error (each flight against the confirmed track GOSPA pairs it with, scans 10 on) is
    within 10 % of the single-target IMM's (``real-imm-singer``'s own ``track``) run on each flight's own plots."""
    import torch
    from tensordict import TensorDict

    from immnet import keys
    from immnet.filters.methods import build_method
    from immnet.imm.measurement import Isotropic

    rng = np.random.default_rng(13)
    r, dt, T = 40.0, 2.0, 40
    method = build_method("real-imm-singer")
    method.measurement, method.needs = Isotropic(r), ()
    ours, told = [], []
    for _ in range(10):
        starts = rng.uniform([-10e3, -10e3, 3e3], [10e3, 10e3, 8e3], (3, 3))
        vels = np.concatenate([rng.uniform(-200, 200, (3, 2)), rng.uniform(-5, 5, (3, 1))], 1)
        z_true = np.full((3, T, 3), np.nan)
        truth = np.zeros((3, T, 3))
        tracker = MultiTargetTracker("real-imm-singer", r=r)
        for k, (t, tr, plots, is_true) in enumerate(_scene(rng, starts, vels, T, dt, r, pd=0.95, clutter=10.0)):
            truth[:, k] = tr
            z_true[is_true[is_true >= 0], k] = plots[is_true >= 0]
            reps = tracker.step(t, plots)
            if k >= 10:
                est = np.array([p.state[0::3] for p in reps]).reshape(-1, 3)
                g = gospa(tr, est, c=500.0)
                assert g["n_missed"] == 0
                ours.extend(np.linalg.norm(est[g["assignment"]] - tr, axis=1))
        batch = TensorDict({keys.MEASUREMENTS: torch.tensor(z_true), keys.DT: torch.full((3,), dt, dtype=torch.float64)},
                           batch_size=[3])
        x = method.track(batch)[keys.STATE].numpy()
        told.extend(np.linalg.norm(x[:, 10:, 0::3] - truth[:, 10:], axis=-1).ravel())
    assert np.mean(ours) == pytest.approx(np.mean(told), rel=0.10)


def test_refusals_name_what_is_wrong():
    """Bad settings and bad scans: one ValueError naming the problem; the tracker is unchanged by a refused scan."""
    for kwargs, msg in (({"confirm": (1, 3)}, r"confirm \(M, N\) needs 2 <= M <= N"),
                        ({"confirm": (5, 4)}, r"confirm \(M, N\) needs 2 <= M <= N"),
                        ({"confirm": "x"}, r"confirm must be \(M, N\)"),
                        ({"confirm": "x"}, r"confirm must be \(M, N\) or a TrackScore, got 'x'"),
                        ({"associator": "nn"}, "associator must be one of gnn, jpda"),
                        ({"gate": 1.0}, r"gate is a probability in \(0, 1\)"),
                        ({"delete_after": 0}, "delete_after must be a whole number of scans >= 1"),
                        ({"pd": 0.0}, r"pd is a probability in \(0, 1\]"),
                        ({"r": -1.0}, "r must be finite and > 0")):
        with pytest.raises(ValueError, match=msg):
            MultiTargetTracker("real-imm-singer", **kwargs)
    with pytest.raises(TypeError, match="init must be a TwoPointStart, got dict"):
        MultiTargetTracker("real-imm-singer", init={"vz_std": 5.0})
    # the start refuses its own bad settings when it is made, in one line each
    for kwargs, msg in (({"vz_std": 0.0}, r"vz_std \(the start's prior std of the vertical speed, m/s\) must be a "
                                          r"number > 0 or None, got 0.0"),
                        ({"p_cv": 1.0}, r"TwoPointStart.p_cv is a probability in \(0, 1\), got 1.0"),
                        ({"p_cv": 0.0}, r"TwoPointStart.p_cv is a probability in \(0, 1\), got 0.0"),
                        ({"max_speed": 0.0}, r"TwoPointStart.max_speed must be finite and > 0, got 0.0"),
                        ({"sigma": float("nan")}, r"TwoPointStart.sigma must be finite and > 0, got nan")):
        with pytest.raises(ValueError, match=msg):
            TwoPointStart(**kwargs)
    with pytest.raises(ValueError, match="the multi-target tracker's filters are the model-based IMMs"):
        TrackFilter.from_method("clairvoyant")
    tracker = MultiTargetTracker("real-imm-singer")  # r: data, so plots need R
    with pytest.raises(ValueError, match=r"plots without R need the tracker's r \(m\): real-imm-singer assumes none"):
        tracker.step(0.0, np.zeros((1, 3)))
    tracker = MultiTargetTracker("real-imm-singer", r=30.0)
    tracker.step(0.0, np.ones((1, 3)))
    for args, msg in (((1.0, np.zeros((2, 2))), r"plots must be an array \[N, 3\] of ENU positions \(m\)"),
                      ((1.0, np.array([[0.0, np.nan, 0.0]])), "plot 0 has a non-finite coordinate"),
                      ((1.0, np.zeros((1, 3)), np.eye(3)[None].repeat(2, 0)), r"R must be \[N, 3, 3\] for the 1 plots"),
                      ((1.0, np.zeros((1, 3)), -np.eye(3)[None]), r"R\[0\] is not a finite symmetric positive-definite"),
                      ((0.0, np.zeros((1, 3))), "scan times must increase, got t = 0.0 after 0.0"),
                      ((float("nan"), np.zeros((1, 3))), "t must be finite")):
        with pytest.raises(ValueError, match=msg):
            tracker.step(*args)
    assert tracker._t == 0.0 and tracker._scan == 0 and len(tracker.seed_z) == 1
