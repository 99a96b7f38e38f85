"""A bank of networks (immnet.tracking.bank): each member's predictive likelihood against FilterPy's IMM, the bank's
member probabilities against the static multiple-model posterior computed from FilterPy's likelihoods in float64,
its estimate and covariance against the mixture of the members' own outputs, members chosen by scan interval, and
bad input refused by name."""

import numpy as np
import pytest
import torch
from filterpy.kalman import IMMEstimator, KalmanFilter

from immnet import keys
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.data.times import scan_intervals
from immnet.filters.methods import build_method
from immnet.filters.imm import initial_state
from immnet.motion import measurement_matrix
from immnet.tracking.bank import PRUNE_AFTER, BankMethod, NetworkBank, accepts
from immnet.tracking.tracker import Tracker, load_network
from immnet.checkpoints import shipped


@pytest.fixture(scope="module")
def data():
    td = generate(5, seed=12, spec=DataSpec(T=70, min_segment=20))
    td[keys.MEASUREMENTS][1, 30:33] = float("nan")  # missed detections inside a track
    td[keys.MEASUREMENTS][3, :2] = float("nan")  # a track first detected at scan 2
    return td


def _filterpy_logliks(method, z: np.ndarray) -> np.ndarray:
    """Each scan's ``log sum_j cbar_j L_j`` of FilterPy's IMMEstimator for one track of ``z [T, 3]`` with the
    method's F, Q, Pi, mu0 and r, started at the first detection as the core starts; NaN up to that scan, 0 where
    the scan has no detection."""
    F, Q, Pi, mu0 = (v.numpy() for v in method.matrices(1.0))
    r = float(method.r)
    zt = torch.from_numpy(z)[None]
    x0, P0 = (v[0].numpy() for v in initial_state(zt, r))
    first = int(np.flatnonzero(~np.isnan(z).any(-1))[0])
    filters = []
    for m in range(F.shape[0]):
        kf = KalmanFilter(9, 3)
        kf.H, kf.R, kf.F, kf.Q = measurement_matrix().numpy(), r * r * np.eye(3), F[m], Q[m]
        kf.x, kf.P = x0.copy(), P0.copy()
        filters.append(kf)
    imm = IMMEstimator(filters, mu0.copy(), Pi)
    out = np.full(len(z), np.nan)
    for t in range(first + 1, len(z)):
        imm.predict()
        if np.isnan(z[t]).any():
            imm.mu = imm.cbar.copy()
            imm._compute_mixing_probabilities()
            imm._compute_state_estimate()
            out[t] = 0.0
        else:
            cbar = imm.cbar.copy()  # the predicted mode probabilities (update recomputes cbar for the next scan)
            imm.update(z[t])
            out[t] = np.log(np.dot(cbar, np.exp([kf.log_likelihood for kf in filters])))
    return out


@pytest.mark.parametrize("method", ["imm-tuned", "imm-min"])
def test_a_networks_predictive_likelihood_is_filterpys_imm_likelihood(data, method):
    """``IMMNet.predictive_loglik`` of a model-based IMM written as IMMNet (``network()``) is, at every scan after
    the start, ``log sum_j cbar_j L_j`` of FilterPy's IMMEstimator with the same models (its predicted mode
    probabilities and its filters' likelihoods), to 1e-6; 0 at a missed detection, NaN before the track predicts."""
    tracker = build_method(method)
    net = tracker.network().double()
    z = data[keys.MEASUREMENTS].double()
    with torch.no_grad():
        out, _ = net.rollout(z, return_loglik=True)
    ours = out[keys.LOGLIK].numpy()
    for b in range(z.shape[0]):
        ref = _filterpy_logliks(tracker, z[b].numpy())
        assert np.array_equal(np.isnan(ours[b]), np.isnan(ref))
        np.testing.assert_allclose(ours[b][~np.isnan(ref)], ref[~np.isnan(ref)], rtol=1e-6, atol=1e-6)
    assert (ours[1, 30:33] == 0).all()
    assert np.isnan(ours[3, :3]).all() and np.isfinite(ours[3, 3:]).all()


@pytest.mark.parametrize("temper", [1.0, 0.5])
def test_the_banks_weights_are_the_static_multiple_model_posterior(data, temper):
    """Two model-based IMMs in a bank: each scan's member probabilities are ``softmax(log prior + temper x cumulative
    log-likelihood)`` from FilterPy's likelihoods in float64 (to 1e-3: the members run in float32, whose
    likelihoods at a track's first scans, with a start covariance of 1e4 m^2/s^2, carry 1e-3 of rounding), the estimate is
    the members' own ``Tracker.track`` estimates so weighted, the covariance the mixture's
    ``sum_k p_k (P_k + (x_k - x)(x_k - x)^T)``, the mode probabilities the members' weighted; a bank of one is the
    member exactly."""
    names = ["imm-tuned", "imm-min"]
    methods = [build_method(n) for n in names]
    nets = {n: m.network().float() for n, m in zip(names, methods)}
    prior = [0.3, 0.7]
    bank = NetworkBank(nets, prior=prior, temper=temper)  # no output correction: "reported" is the filters' own
    z = data[keys.MEASUREMENTS].float()
    intervals = torch.ones(z.shape[:2], dtype=torch.float64)
    out = bank.track(z, intervals=intervals, return_cov=True)
    own = [Tracker(net).track(z, return_cov=True) for net in nets.values()]
    w = out[keys.MEMBER_PROBS]
    for b in range(z.shape[0]):
        L = np.stack([_filterpy_logliks(m, z[b].double().numpy()) for m in methods], -1)
        weighed = np.isfinite(L).all(-1, keepdims=True)
        log_w = np.log(np.array(prior) / sum(prior)) + temper * np.cumsum(np.where(weighed, L, 0.0), 0)
        ref = np.exp(log_w - log_w.max(-1, keepdims=True))
        ref /= ref.sum(-1, keepdims=True)
        seen = ~np.isnan(w[b, :, 0].numpy())
        np.testing.assert_allclose(w[b].numpy()[seen], ref[seen], rtol=0, atol=1e-3)
    x = torch.stack([o[keys.STATE].double() for o in own], -2)  # [B, T, K, 9]
    fused = (w[..., None] * x).sum(-2)
    torch.testing.assert_close(out[keys.STATE], fused, equal_nan=True, rtol=0, atol=1e-9)
    d = x - fused[..., None, :]
    P = torch.stack([o[keys.STATE_COV].double() for o in own], -3) + d[..., :, None] * d[..., None, :]
    torch.testing.assert_close(out[keys.STATE_COV], (w[..., None, None] * P).sum(-3), equal_nan=True, rtol=0, atol=1e-9)
    probs = torch.stack([o[keys.MODE_PROBS].double() for o in own], -2)
    torch.testing.assert_close(out[keys.MODE_PROBS], (w[..., None] * probs).sum(-2), equal_nan=True, rtol=0, atol=1e-12)
    assert torch.isnan(out[keys.STATE][3, :2]).all() and torch.isfinite(out[keys.STATE][3, 2:]).all()
    # one member: its own output, exactly
    alone = NetworkBank({"imm-tuned": nets["imm-tuned"]}).track(z, intervals=intervals, return_cov=True)
    torch.testing.assert_close(alone[keys.STATE], own[0][keys.STATE].double(), equal_nan=True, rtol=0, atol=0)
    torch.testing.assert_close(alone[keys.STATE_COV], own[0][keys.STATE_COV].double(), equal_nan=True, rtol=0, atol=0)


def test_the_reported_tracks_likelihood_is_the_filters_moved_by_the_correction(data):
    """A network with an output correction (the shipped ``real``): ``shifted_loglik`` is, per axis and filter
    expert, ``log N(z - H x_prior - shift; 0, P_prior + r^2)`` (scipy, float64), and with no shift the filter's own
    likelihood; ``predictive_loglik(reported=True)`` moves each prediction by the correction reported at the scan
    before (``before``'s output less its fused estimate): the same as the filter's likelihood of the measurement moved
    the other way, and the filter's own where ``before`` holds no report."""
    from scipy.stats import norm

    net = load_network(shipped("real"))
    z = data[keys.MEASUREMENTS].float()
    with torch.no_grad():
        carry = net.initial_carry(z.shape[0])
        for t in range(12):
            before, carry = carry, net.scan(carry, z[:, t])
        after = carry
        shift = torch.tensor([[0.7, -1.3, 0.4]]).expand(z.shape[0], 3)
        ll = net.gain.shifted_loglik(after, shift)  # [B, 3 axes, M]
        torch.testing.assert_close(net.gain.shifted_loglik(after, torch.zeros_like(shift)), after.get(keys.EXPERT_LOGLIK),
                                   rtol=0, atol=1e-5)
        x = after.get(keys.EXPERT_PRIOR).double()
        P = after.get(keys.EXPERT_AUG_PRIOR_COV).double()
        r2 = after.get(keys.NOISE_VAR).double()
        for b in range(z.shape[0]):
            for a in range(3):
                for m in range(x.shape[1]):
                    ref = norm.logpdf(float(z[b, 11, a]) - float(x[b, m, 3 * a]) - float(shift[b, a]), 0.0,
                                      np.sqrt(float(P[b, m, 3 * a, 3 * a] + r2[b])))
                    assert float(ll[b, a, m]) == pytest.approx(ref, abs=1e-4)
        # reported: before's correction moves the prediction, as the measurement moved the other way would
        moved = before.clone()
        moved.set(keys.OUTPUT, before.get(keys.FUSED) + torch.tensor([0.5, 0.0, 0.0, -2.0, 0.0, 0.0, 1.0, 0.0, 0.0]))
        got = net.predictive_loglik(moved, after, reported=True)
        other = after.clone()
        other.set(keys.MEASUREMENT, after.get(keys.MEASUREMENT) - torch.tensor([0.5, -2.0, 1.0]))
        other.set(keys.EXPERT_LOGLIK, net.gain.shifted_loglik(other, torch.zeros_like(shift)))
        torch.testing.assert_close(got, net.predictive_loglik(moved, other), rtol=0, atol=1e-5)
        assert not torch.allclose(got, net.predictive_loglik(moved, after))
        bare = before.select(*net.carry_keys)  # no report kept: the filter's own
        torch.testing.assert_close(net.predictive_loglik(bare, after, reported=True), net.predictive_loglik(bare, after))
        # a rollout weighs the reported track scan by scan: its first scan after the start, the filter's
        out, _ = net.rollout(z, return_loglik="reported")
        plain, _ = net.rollout(z, return_loglik=True)
        assert torch.equal(torch.isnan(out[keys.LOGLIK]), torch.isnan(plain[keys.LOGLIK]))
        assert not torch.allclose(out[keys.LOGLIK].nan_to_num(), plain[keys.LOGLIK].nan_to_num())


def test_a_banks_likelihood_and_temper_are_checked_by_name():
    net = build_method("imm-tuned").network().float()
    with pytest.raises(ValueError, match="likelihood is one of filter, reported, got 'best'"):
        NetworkBank({"a": net}, likelihood="best")
    for bad in (0, 1.5, float("nan")):
        with pytest.raises(ValueError, match="temper is a number in \\(0, 1\\]"):
            NetworkBank({"a": net}, temper=bad)


def test_each_member_tracks_the_scans_it_was_trained_for():
    """The shipped bank in a batch of 1 s, 5 s and 11.5 s tracks: the 1 s networks (real flights, 3D-LAST) take only the
    1 s tracks, the 5 s one only the 5 s tracks, the 10-12 s one only the 11.5 s track, the 4.5-12 s one both of these,
    the general network all but those the 3D-LAST network takes (``DEFER``); a bank of the general network alone gives
    its estimate to the bit. A bank none of whose
    members takes a track refuses it by name."""
    general, real = load_network(shipped("general")), load_network(shipped("real"))
    assert accepts(real, torch.ones(2, 5)).all() and not accepts(real, torch.full((1, 5), 5.0)).any()
    assert accepts(general, torch.tensor([[1.0, 0.5, 30.0]])).all()  # a long gap is coasted, at 10 s
    assert not accepts(general, torch.tensor([[1.0, 0.2, 1.0]])).any()
    real5 = load_network(shipped("real-5s"))  # 4.5-5.5 s: a 10 s gap is two 5 s scans, a 6.25 s one would be 3.125 s
    assert accepts(real5, torch.tensor([[5.0, 4.6, 10.0, 5.4]])).all()
    assert not accepts(real5, torch.tensor([[5.0, 6.25, 5.0]])).any()
    real11 = load_network(shipped("real-11s"))  # 10-12 s: a 22 s gap is two 11 s scans, a 13 s one would be 6.5 s
    assert accepts(real11, torch.tensor([[11.0, 10.2, 22.0, 11.8]])).all()
    assert not accepts(real11, torch.tensor([[11.0, 13.0, 11.0]])).any()
    assert not accepts(real11, torch.full((1, 5), 5.0)).any() and not accepts(real5, torch.full((1, 5), 11.5)).any()
    assert accepts(real5, torch.full((1, 5), 11.0)).all()  # two 5.5 s scans, one of them missed
    bank = BankMethod()
    td = generate(4, seed=3, spec=DataSpec(T=45, min_segment=15))
    td5 = generate(2, seed=4, spec=DataSpec(T=45, min_segment=15, dt=5.0))
    td11 = generate(1, seed=5, spec=DataSpec(T=45, min_segment=15, dt=11.5))
    z = torch.cat([td[keys.MEASUREMENTS], td5[keys.MEASUREMENTS], td11[keys.MEASUREMENTS]]).float()
    iv = torch.cat([torch.ones(4, 45), torch.full((2, 45), 5.0), torch.full((1, 45), 11.5)]).double()
    takes = bank.net.takes(iv)
    assert bank.net.names == ["general", "real", "real-5s", "real-11s", "real-4.5-12s", "3dlast"]
    assert takes.tolist() == ([[False, True, False, False, False, True]] * 4 + [[True, False, True, False, True, False]] * 2
                              + [[True, False, False, True, True, False]])
    out = bank.net.track(z, intervals=iv)
    w = out[keys.MEMBER_PROBS].nan_to_num(0)
    assert (w[~takes[:, None, :].expand_as(w)] == 0).all()  # a member that does not take a track has no weight in it
    assert (w[6, 10:PRUNE_AFTER, 3] > 0).all()  # the 11 s track: the 10-12 s network in the mixture (until pruned)
    torch.testing.assert_close(w.sum(-1), torch.ones(7, 45, dtype=torch.float64), rtol=0, atol=1e-12)
    only = NetworkBank({"general": general}).track(z[4:], intervals=iv[4:])
    alone = Tracker(general).track(z[4:], intervals=iv[4:])
    torch.testing.assert_close(only[keys.STATE], alone[keys.STATE].double(), equal_nan=True, rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"no member of this bank takes track\(s\) 4, 5, 6: the first has scan intervals of 5 to 5 s.*real 1 s"):
        NetworkBank({"real": real}).track(z, intervals=iv)


def test_a_bank_refuses_bad_members_by_name():
    net = build_method("imm-tuned").network().float()
    with pytest.raises(ValueError, match="at least one member"):
        NetworkBank({})
    with pytest.raises(ValueError, match="one positive number per member"):
        NetworkBank({"a": net}, prior=[1.0, 2.0])
    with pytest.raises(ValueError, match="one positive number per member"):
        NetworkBank({"a": net}, prior=[0.0])
    with pytest.raises(ValueError, match="named once each"):
        NetworkBank.from_names(["real", "real"])
    with pytest.raises(FileNotFoundError, match="no-such.ckpt"):
        NetworkBank.from_names(["no-such.ckpt"])
    told = build_method("real-ca").network().float()
    with pytest.raises(ValueError, match="'told' is told each track's measurement std"):
        NetworkBank({"told": told})
    with pytest.raises(ValueError, match="intervals are"):
        NetworkBank({"a": net}).track(torch.zeros(2, 5, 3), intervals=torch.ones(2, 4))


@pytest.fixture(scope="module")
def shipped_bank():
    return NetworkBank.from_names()  # the shipped bank


def test_streaming_gives_the_banks_whole_sequence_numbers(shipped_bank):
    """``NetworkBank.step`` over a sequence is ``track`` to the bit (estimate, covariance, member probabilities), with
    missed detections and a late start; a reset restarts a track with every member at its prior (the restarted
    track as the bank tracks it alone from there); a scan after an interval only the general network takes leaves it
    alone in the track from then on; a scan no member still in the track takes is refused before anything changes."""
    bank = shipped_bank
    td = generate(3, seed=3, spec=DataSpec(T=45, min_segment=15))
    z = td[keys.MEASUREMENTS].float()
    z[1, :3] = float("nan")
    z[2, 20:22] = float("nan")
    ref = bank.track(z, return_cov=True)
    bank.reset(3)
    outs = [bank.step(z[:, t]) for t in range(45)]
    for key, name in ((keys.FUSED, keys.STATE), (keys.FUSED_COV, keys.STATE_COV), (keys.MEMBER_PROBS, keys.MEMBER_PROBS),
                      (keys.MODE_PROBS, keys.MODE_PROBS)):
        torch.testing.assert_close(torch.stack([o[key] for o in outs], 1), ref[name], equal_nan=True, rtol=0, atol=0)
    assert torch.isnan(outs[1][keys.FUSED][1]).all() and torch.isfinite(outs[3][keys.FUSED][1]).all()
    # a reset: track 1 again from scan 20, as the bank tracks that part alone
    bank.reset(3)
    got = [bank.step(z[:, t], reset=torch.tensor([False, t == 20, False])) for t in range(45)]
    alone = bank.track(z[1:2, 20:])
    torch.testing.assert_close(torch.stack([o[keys.FUSED][1] for o in got[20:]]), alone[keys.STATE][0], rtol=0, atol=1e-3)
    torch.testing.assert_close(torch.stack([o[keys.MEMBER_PROBS][1] for o in got[20:]]), alone[keys.MEMBER_PROBS][0],
                               rtol=0, atol=1e-3)
    # a 5 s interval at scan 10: the 1 s networks leave the track, the general one carries it
    bank.reset(1)
    w = torch.stack([bank.step(z[:1, t], dt=5.0 if t == 10 else 1.0)[keys.MEMBER_PROBS][0] for t in range(20)])
    assert (w[2:10, 1] > 0).all() and (w[:, 2] == 0).all() and (w[10:, 0] == 1).all()
    # refused before anything changes
    real = NetworkBank.from_names(["real"])
    real.reset(2)
    first = real.step(z[:2, 0])
    with pytest.raises(ValueError, match=r"no member of this bank still in track\(s\) 0, 1 takes a scan after 5 s"):
        real.step(z[:2, 1], dt=5.0)
    again = NetworkBank.from_names(["real"])
    again.reset(2)
    again.step(z[:2, 0])
    torch.testing.assert_close(real.step(z[:2, 1])[keys.FUSED], again.step(z[:2, 1])[keys.FUSED], equal_nan=True, rtol=0,
                               atol=0)
    assert first[keys.MEMBER_PROBS][0, 0] == 1 and torch.isnan(first[keys.MEMBER_PROBS][1]).all()  # track 1: no detection yet


def test_streaming_coasts_a_long_interval_as_the_whole_sequence_does(shipped_bank):
    """At scans 9-11 s apart (and one 20 s gap) ``track`` cuts each interval for real-5s (4.5-5.5 s) into two scans,
    the first missed; ``step`` does the same, so that real-5s stays in the track and streaming gives ``track``'s
    numbers to the bit (estimate, covariance, member and mode probabilities) with missed detections, a late start,
    one track coasting longer than the others, and a reset."""
    bank = shipped_bank
    td = generate(3, seed=7, spec=DataSpec(T=30, min_segment=10, dt=10.0, dt_jitter=1.0))
    z = td[keys.MEASUREMENTS].float()
    iv = scan_intervals(td).clone()
    iv[:, 0] = iv[1, 10] = 9.5  # a track's first scan: no member but those of the whole track takes it
    iv[0, 12] = 20.0  # general and real-4.5-12s coast it as two 10 s scans, real-5s as four of 5 s
    z[1, :2] = float("nan")
    z[2, 15:17] = float("nan")
    ref = bank.track(z, intervals=iv, return_cov=True)
    takes = bank.takes(iv)
    assert takes[:, [0, 2, 4]].all() and not takes[:, [1, 3, 5]].any()  # real-5s coasts every other scan
    assert (ref[keys.MEMBER_PROBS][:, 5:, 2] > 1e-3).any()  # and carries weight
    bank.reset(3)
    outs = [bank.step(z[:, t], dt=iv[:, t]) for t in range(30)]
    for key, name in ((keys.FUSED, keys.STATE), (keys.FUSED_COV, keys.STATE_COV),
                      (keys.MEMBER_PROBS, keys.MEMBER_PROBS), (keys.MODE_PROBS, keys.MODE_PROBS)):
        torch.testing.assert_close(torch.stack([o[key] for o in outs], 1), ref[name], equal_nan=True, rtol=0, atol=0)
    # a reset at scan 10: that track again from there, its first interval nominal
    bank.reset(3)
    got = [bank.step(z[:, t], reset=torch.tensor([False, t == 10, False]), dt=iv[:, t]) for t in range(30)]
    alone = bank.track(z[1:2, 10:], intervals=iv[1:2, 10:])  # a batch of one: float32 rounding of positions
    torch.testing.assert_close(torch.stack([o[keys.FUSED][1] for o in got[10:]]), alone[keys.STATE][0], rtol=1e-5,
                               atol=1e-3)
    torch.testing.assert_close(torch.stack([o[keys.MEMBER_PROBS][1] for o in got[10:]]), alone[keys.MEMBER_PROBS][0],
                               rtol=0, atol=1e-3)


def test_immnet_track_with_the_bank_tracks_each_row_at_its_own_time(tmp_path, shipped_bank):
    """``immnet track --weights bank``: a CSV of a track scanned every 1 s and one every 5 s gives the bank's numbers
    for each (``NetworkBank.track`` of each track at its intervals, to the CSV's digits), the covariance columns
    filled; an .npz gives them too, with each member's probability (``member_probs``, ``member_names``)."""
    import csv

    from immnet.cli import main

    rng = np.random.default_rng(4)
    tracks = {"a": np.arange(60) * 1.0, "b": np.arange(30) * 5.0}
    rows, z = [], {}
    for name, t in tracks.items():
        p = np.stack([8e3 + 150 * t, -5e3 + 40 * t + 0.05 * t**2, 3e3 + 2 * t], -1)
        z[name] = p + rng.normal(0, 4.0, p.shape)
        rows += [(name, f"{ti:.1f}", *(repr(float(v)) for v in zi)) for ti, zi in zip(t, z[name])]
    with open(tmp_path / "in.csv", "w", newline="") as f:
        csv.writer(f).writerows([("track_id", "t", "x", "y", "z"), *rows])
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(tmp_path / "out.csv"),
                 "--weights", "bank"]) == 0
    with open(tmp_path / "out.csv") as f:
        out = list(csv.DictReader(f))
    for name, t in tracks.items():
        mine = [r for r in out if r["track_id"] == name]
        got = np.array([[float(r[c]) for c in ("x", "vx", "y", "vy", "z", "vz")] for r in mine])
        iv = torch.tensor(np.r_[np.median(np.diff(t)), np.diff(t)][None])
        ref = shipped_bank.track(torch.from_numpy(z[name][None]).float(), intervals=iv)[keys.STATE][0]
        # to 1 cm: in the CSV's batch the 5 s track has the general network step at explicit intervals, the 1 s
        # track with it (float32 rounding, 3 mm here), where alone it steps at its own
        np.testing.assert_allclose(got, ref[:, [0, 1, 3, 4, 6, 7]].numpy(), rtol=0, atol=1e-2)
        assert all(r["cov_xx"] != "" and float(r["cov_xx"]) > 0 for r in mine)
    np.savez(tmp_path / "in.npz", measurements=z["b"][None].astype(np.float32), dt=5.0)
    assert main(["track", "--input", str(tmp_path / "in.npz"), "--output", str(tmp_path / "out.npz"),
                 "--weights", "bank"]) == 0
    npz = np.load(tmp_path / "out.npz")
    assert list(npz["member_names"]) == ["general", "real", "real-5s", "real-11s", "real-4.5-12s", "3dlast"]
    ref = shipped_bank.track(torch.from_numpy(z["b"][None]).float(), intervals=torch.full((1, 30), 5.0))
    np.testing.assert_allclose(npz["state"], ref[keys.STATE].numpy(), rtol=0, atol=0)
    np.testing.assert_allclose(npz["member_probs"][0, 5:].sum(-1), 1.0, rtol=1e-12)
    assert (npz["member_probs"][0, :, [1, 3, 5]] == 0).all() and npz["state_cov"].shape == (1, 30, 9, 9)
