"""A shipped network as the multi-target tracker's per-track filter (``immnet.tracking.network_filter``): each track is
the network run alone on its plots, tracks added and dropped leave the others as they were, the gate's prediction is
the network's own, and the refusals (docs/multi-target.md, "The tracker")."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from immnet import keys
from immnet.filters.multi import MultiTargetTracker, TrackFilter
from immnet.tracking.tracker import Tracker

NETWORKS = ("radar-5s", "real-5s")  # told each plot's covariance; estimating its own noise
R_PLOT = np.diag([40.0, 60.0, 30.0]) ** 2


def _flights(rng, T, n=3):
    """``n`` straight flights at 4.5-5.5 s scans: times ``t [T]`` and plots ``z [n, T, 3]`` (noise ``R_PLOT``)."""
    t = np.cumsum(rng.uniform(4.5, 5.5, T))
    starts = np.array([[30e3, 20e3, 8e3], [-25e3, 10e3, 6e3], [5e3, -40e3, 9e3]])[:n]
    vels = np.array([[150.0, -80.0, 2.0], [-200.0, 30.0, 0.0], [100.0, 180.0, -3.0]])[:n]
    truth = starts[:, None] + vels[:, None] * (t - t[0])[None, :, None]
    return t, truth + rng.multivariate_normal(np.zeros(3), R_PLOT, (n, T))


def _alone(name, t, z, missed=()):
    """The network alone on one track's plots (``Tracker.step``, scan by scan; the first scan at the second's
    interval, as the tracker's two-point start takes it; ``missed``: scans without a plot), without its own start prior
    on the vertical speed as the multi-target tracker loads it (``NetworkFilter.pretrained``): its reported state and
    covariance per scan."""
    tr = Tracker.pretrained(name)
    tr.max_coast = float("inf")
    tr.net.gain.start_vz_std = None
    told = tr.net.start.told_cov
    out = []
    for k in range(len(t)):
        dt = t[1] - t[0] if k == 0 else t[k] - t[k - 1]
        zk = np.full((1, 3), np.nan) if k in missed else z[None, k]
        kw = {"R": torch.from_numpy(R_PLOT[None] if k not in missed else np.eye(3)[None])} if told else {}
        o = tr.step(torch.from_numpy(zk), dt=dt, **kw)
        out.append((o.get(keys.FUSED)[0].double().numpy(), o.get(keys.FUSED_COV)[0].double().numpy()))
    return out


@pytest.mark.parametrize("name", NETWORKS)
def test_one_track_in_an_empty_scene_is_the_network_alone(name):
    """One flight, no clutter, a missed scan: the multi-target tracker's track (started from the first two plots) has
    at every scan the state and covariance of the network run alone on the flight's plots, to the bit."""
    rng = np.random.default_rng(0)
    t, z = _flights(rng, 20, n=1)
    missed = {9}
    tracker = MultiTargetTracker(name)
    got = {}
    for k in range(len(t)):
        plots = np.zeros((0, 3)) if k in missed else z[0, k:k + 1]
        tracker.step(t[k], plots, np.broadcast_to(R_PLOT, (len(plots), 3, 3)))
        (rep,) = tracker.tracks() if k else (None,)
        if k:
            got[k] = rep
    assert [k for k, r in got.items() if not r.updated] == [9]
    ref = _alone(name, t, z[0], missed)
    for k, rep in got.items():
        np.testing.assert_array_equal(rep.state, ref[k][0])
        np.testing.assert_array_equal(rep.cov, ref[k][1])


@pytest.mark.parametrize("name", NETWORKS)
def test_prediction_is_the_networks_coast(name):
    """``predict`` gives the position and covariance the network reports after a scan without a detection (its own
    prediction), plus, for a network with its own measurement noise, its noise estimate ``r^2 I``; and it leaves the
    tracks as they were: predicting twice gives the same, and the update after it is the network's scan."""
    rng = np.random.default_rng(1)
    t, z = _flights(rng, 8, n=1)
    f = TrackFilter.by_name(name)
    f.start(z[0, 1:2], R_PLOT[None], z[0, 0:1], R_PLOT[None], t[1] - t[0])
    for k in range(2, 6):
        f.predict(t[k] - t[k - 1])
        f.update(z[0, k:k + 1], R_PLOT[None])
    x_before = f.state()[0].copy()
    pos, S = f.predict(t[6] - t[5])
    pos2, S2 = f.predict(t[6] - t[5])
    np.testing.assert_array_equal(pos, pos2)
    np.testing.assert_array_equal(S, S2)
    np.testing.assert_array_equal(f.state()[0], x_before)
    ref = _alone(name, t[:7], z[0, :7], missed={6})
    x_coast, P_coast = ref[6]
    np.testing.assert_array_equal(pos[0], x_coast[0::3])
    if f.plot_noise:  # told the plot's covariance: the tracker adds it per plot
        np.testing.assert_array_equal(S[0], P_coast[0::3, 0::3])
    else:  # its own noise: the estimate it carries, the same in every axis
        extra = S[0] - P_coast[0::3, 0::3]
        assert np.allclose(extra, extra[0, 0] * np.eye(3), rtol=0, atol=1e-6 * extra[0, 0]) and extra[0, 0] > 0
        r2 = f._tr.carry.get(keys.NOISE_VAR)
        assert extra[0, 0] == pytest.approx(float(r2[0]), rel=1e-12)
    f.update(z[0, 6:7], R_PLOT[None])
    np.testing.assert_array_equal(f.state()[0][0], _alone(name, t[:7], z[0, :7])[6][0])


@pytest.mark.parametrize("name", NETWORKS)
def test_tracks_added_and_dropped_leave_the_others_unchanged(name):
    """Tracks A and B start together, C starts four scans later, B is dropped at scan 6: A's and C's states at every
    scan are those of A alone and C alone (one track per filter), to float32 rounding in the network's frame."""
    rng = np.random.default_rng(3)
    T = 12
    t, z = _flights(rng, T)
    Rk = lambda n: np.broadcast_to(R_PLOT, (n, 3, 3)).copy()
    f, a, c = (TrackFilter.by_name(name) for _ in range(3))
    f.start(z[:2, 1], Rk(2), z[:2, 0], Rk(2), t[1] - t[0])
    a.start(z[:1, 1], Rk(1), z[:1, 0], Rk(1), t[1] - t[0])
    rows = [0, 1]  # the flight of each row of f
    checked = 0
    for k in range(2, T):
        dt = t[k] - t[k - 1]
        for g in (f, a) + ((c,) if k > 4 else ()):
            g.predict(dt)
        f.update(z[rows, k], Rk(len(rows)))
        a.update(z[:1, k], Rk(1))
        if k > 4:
            c.update(z[2:3, k], Rk(1))
        if k == 4:
            f.start(z[2:3, k], Rk(1), z[2:3, k - 1], Rk(1), dt)
            c.start(z[2:3, k], Rk(1), z[2:3, k - 1], Rk(1), dt)
            rows.append(2)
        if k == 6:
            f.drop(np.array([True, False, True]))
            rows = [0, 2]
        x, P = f.state()
        assert len(f) == len(rows)
        np.testing.assert_allclose(x[0], a.state()[0][0], rtol=1e-7, atol=1e-4)
        np.testing.assert_allclose(P[0], a.state()[1][0], rtol=1e-5, atol=1e-4)
        if k >= 4:
            np.testing.assert_allclose(x[rows.index(2)], c.state()[0][0], rtol=1e-7, atol=1e-4)
            checked += 1
    assert checked == T - 4
    f.drop(np.zeros(2, bool))
    assert len(f) == 0 and f.state()[0].shape == (0, 9)
    f.start(z[:1, 1], Rk(1), z[:1, 0], Rk(1), t[1] - t[0])  # an emptied filter starts again
    np.testing.assert_array_equal(f.state()[0][0], _alone(name, t[:2], z[0, :2])[1][0])


def test_a_network_of_one_interval_coasts_between_a_seed_and_its_pair():
    """``real`` (trained at 1 s alone, on flights' positions of a few metres' noise: its own noise estimate gates),
    1 s scans. Flight A's plot is missed at scan 1: its seed (scan 0) pairs with scan 2's plot; flight B appears at
    scan 1 and its seed pairs at scan 2 too (one start of two tracks, spanning two scans and one). Each track is the
    network alone on its flight's plots (A coasting through scan 1: the interval of 2 s is two of its scans), to
    float32 rounding (two tracks in one batch)."""
    rng = np.random.default_rng(4)
    T = 10
    t = np.arange(T, dtype=np.float64)
    za = np.array([20e3, -10e3, 7e3]) + np.outer(t, [180.0, 60.0, 1.0]) + rng.normal(0, 3.0, (T, 3))
    zb = np.array([-30e3, 15e3, 9e3]) + np.outer(t, [-90.0, 200.0, 0.0]) + rng.normal(0, 3.0, (T, 3))
    tracker = MultiTargetTracker("real", r=3.0)
    got = {}
    for k in range(T):
        plots = [p for p, seen in ((za[k], k != 1), (zb[k], k >= 1)) if seen]
        tracker.step(t[k], np.array(plots).reshape(-1, 3))
        if k >= 2:
            reps = tracker.tracks()
            assert len(reps) == 2
            for rep in reps:  # each track by where it is
                got.setdefault(int(np.linalg.norm(rep.state[0::3] - za[k]) > 1e3), {})[k] = rep
    ref_a = _alone("real", t, za, missed={1})
    ref_b = _alone("real", t[1:], zb[1:])
    for k in range(2, T):
        np.testing.assert_allclose(got[0][k].state, ref_a[k][0], rtol=1e-7, atol=1e-4)
        np.testing.assert_allclose(got[1][k].state, ref_b[k - 1][0], rtol=1e-7, atol=1e-4)


def test_refusals_of_a_network_filter():
    """JPDA with a network, the bank, a network told r per track, a one-point start, a method config of a network, a
    scan at an interval the network does not take: one line each, naming why."""
    with pytest.raises(ValueError, match=r"^radar-5s is a network: JPDA needs a mixture update over a track's gated "
                                         r"plots, .* use GNN \(associator gnn\)$"):
        MultiTargetTracker("radar-5s", associator="jpda")
    with pytest.raises(ValueError, match=r"^bank is several networks weighed per track, not one"):
        MultiTargetTracker("bank")
    from immnet.tracking.network_filter import NetworkFilter

    with pytest.raises(ValueError, match=r"^real-5s is told each track's measurement std \(r='data'\): the "
                                         r"multi-target tracker has none per track to tell it"):
        NetworkFilter(Tracker.pretrained("real-5s", r="data"), "real-5s")
    f = TrackFilter.by_name("radar-5s")
    with pytest.raises(ValueError, match="a network's track starts from two plots"):
        f.start(np.zeros((1, 3)), np.eye(3)[None])
    assert len(f) == 0
    with pytest.raises(ValueError, match="and the shipped networks by their weights' name"):
        TrackFilter.by_name("immnet-radar-5s")
    # a scan at an interval the network does not take: refused before the tracker changes anything
    # (M of N: a track score would drop a pair 16 s apart 4 km from the radar, its start's ball the whole sky seen)
    tracker = MultiTargetTracker("radar-5s", r=30.0, confirm=(4, 5))
    tracker.step(0.0, np.array([[1000.0, 2000.0, 3000.0]]))
    with pytest.raises(ValueError, match=r"^radar-5s was trained on intervals 4.5-5.5 s but this data has an interval "
                                         r"of 2 s, outside that range"):
        tracker.step(2.0, np.array([[1200.0, 2000.0, 3000.0]]))
    assert tracker._t == 0.0 and tracker._scan == 0 and len(tracker.seed_z) == 1 and len(tracker) == 0
    tracker.step(16.0, np.array([[3000.0, 2000.0, 3000.0]]))  # longer than the range: coasted through, taken
    assert len(tracker) == 1


def test_a_network_filter_runs_without_re_acquisition():
    """A track's filter does not restart itself: the multi-target tracker starts and deletes tracks. A shipped radar
    network whose gain carries re-acquisition (``immnet.imm.reacquire``) is loaded without it by name, its weights
    the checkpoint's; one loaded with it is refused in one line."""
    from immnet.checkpoints import shipped
    from immnet.tracking.network_filter import NetworkFilter
    from immnet.tracking.networks import load_network

    f = TrackFilter.by_name("radar-5s")
    assert f.net.gain.reacquire is None
    ref = load_network(shipped("radar-5s"))
    assert all(torch.equal(a, b) for a, b in zip(f.net.state_dict().values(), ref.state_dict().values()))
    with pytest.raises(ValueError) as err:
        NetworkFilter(Tracker(load_network(shipped("radar-5s"), reacquire=True)), "radar-5s")
    assert str(err.value) == ("radar-5s restarts its own tracks (re-acquisition, immnet.imm.reacquire): the "
                              "multi-target tracker starts and deletes them (load it with reacquire=None)")


def test_a_network_filter_starts_without_its_own_vertical_speed_prior():
    """The multi-target tracker starts its tracks: a shipped radar network whose gain fuses a prior on the vertical
    speed at a start (``start_vz_std``) is loaded by name without it (the weights the checkpoint's), and one with it is
    refused in one line. With it, Huber's update takes a pair's second plot 1.5 km above the first as an outlier and the
    track stays wide (the horizontal position's std over 1 km after the pair, against the plots' 50 m without it)."""
    from immnet.checkpoints import shipped
    from immnet.tracking.network_filter import NetworkFilter
    from immnet.tracking.networks import load_network

    own = load_network(shipped("radar-5s"), reacquire=None)
    assert own.gain.start_vz_std is not None
    with pytest.raises(ValueError) as err:
        NetworkFilter(Tracker(own), "radar-5s")
    assert str(err.value) == ("radar-5s starts a track with its own prior on the vertical speed (start_vz_std): the "
                              "multi-target tracker starts them (load it with start_vz_std=None)")
    f = TrackFilter.by_name("radar-5s")
    assert f.net.gain.start_vz_std is None
    loaded = load_network(shipped("radar-5s"), reacquire=None, start_vz_std=None)  # as the refusal says
    assert loaded.gain.start_vz_std is None and loaded.gain.reacquire is None
    NetworkFilter(Tracker(loaded), "radar-5s")
    R = np.eye(3)[None] * 2500.0
    pair = (np.array([[10500.0, 10000.0, 6500.0]]), R, np.array([[10000.0, 10000.0, 5000.0]]), R, np.array([5.0]))
    f.start(*pair)
    assert np.sqrt(f._P[0, 0, 0]) < 60.0
    own.gain.start_vz_std = None  # the same network, its prior put back by hand: the wide track
    wide = NetworkFilter(Tracker(own), "radar-5s")
    own.gain.start_vz_std = 5.0
    wide.start(*pair)
    assert np.sqrt(wide._P[0, 0, 0]) > 1000.0
