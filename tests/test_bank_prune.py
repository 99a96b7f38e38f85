"""The bank's pruning and deferring (immnet.tracking.bank, docs/tracking.md "A bank of networks"): a member whose
probability on a track falls below ``prune`` runs on that track no more, checked against the static multiple-model
posterior with pruning recomputed from each member's own likelihoods; pruning that removes nothing is the bank to the
bit; the general network gives way to the 3D-LAST network on the tracks that one takes, runs on no row of them, and
the bank there is the bank without it."""

import math

import numpy as np
import pytest
import torch

from immnet import keys
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.tracking.bank import DEFER, PRUNE, PRUNE_AFTER, BankMethod, NetworkBank
from immnet.tracking.networks import run_network


@pytest.fixture(scope="module")
def tracks():
    td = generate(6, seed=21, spec=DataSpec(T=80, min_segment=20))
    z = td[keys.MEASUREMENTS].double()
    z[2, 40:43] = float("nan")  # missed detections inside a track
    z[4, :3] = float("nan")  # a track first detected at scan 3
    return z


def _counting(bank: NetworkBank) -> dict[str, list[int]]:
    """Each member's rows per scan it runs, as the bank calls it (``IMMNet.scan``'s batch)."""
    rows = {name: [] for name in bank.names}
    for name, net in bank.members.items():
        def scan(carry, z, *args, _scan=net.scan, _rows=rows[name], **kwargs):
            _rows.append(z.shape[0])
            return _scan(carry, z, *args, **kwargs)
        net.scan = scan
    return rows


@pytest.mark.parametrize("after", [0, 12])
def test_pruning_follows_the_posterior_and_a_pruned_member_runs_no_more(tracks, after):
    """Three networks on 1 s tracks, pruned at 0.01 from the ``after``-th scan since a track's first detection: the
    member probabilities are the static multiple-model posterior recomputed in float64 from each member's own
    likelihoods (each run alone on every track), a member dropped from a track after the first scan from then on its
    probability there is below 0.01 (never the most probable), renormalized over the others; the estimate is the
    members' own estimates so weighted; from the scan after it was dropped, a member runs on that track no more (its
    rows per scan counted)."""
    eps, temper = 0.01, 0.5
    bank = NetworkBank.from_names(["general", "real", "3dlast"], prune=eps, defer={}, prune_after=after)
    z, B, T, K = tracks, tracks.shape[0], tracks.shape[1], 3
    iv = torch.ones(B, T, dtype=torch.float64)
    own = [run_network(net, z, intervals=iv, return_loglik="reported")[0] for net in bank.members.values()]
    L = torch.stack([o[keys.LOGLIK].double() for o in own], -1).numpy()  # [B, T, K]
    x = torch.stack([o[keys.STATE].double() for o in own], -2)  # [B, T, K, 9]
    ref = np.zeros((B, T, K))
    runs = np.zeros((T, K), dtype=int)  # each member's rows per scan
    first = (~torch.isnan(z).any(-1)).int().argmax(-1).tolist()  # each track's first detection
    for b in range(B):
        log_w, alive = np.full(K, math.log(1 / K)), np.ones(K, dtype=bool)
        for t in range(T):
            runs[t] += alive
            if np.isfinite(L[b, t, alive]).all():  # a scan every member still in the track predicted
                log_w = log_w + temper * np.where(alive, np.nan_to_num(L[b, t]), 0.0)
            w = np.where(alive, np.exp(log_w - log_w[alive].max()), 0.0)
            ref[b, t] = w / w.sum()
            if t - first[b] + 1 >= after:
                alive &= ~((ref[b, t] < eps) & (ref[b, t] < ref[b, t].max()))
    rows = _counting(bank)
    out = bank.track(z, intervals=iv)
    seen = ~np.isnan(out[keys.MEMBER_PROBS][..., 0].numpy())
    # to 1e-3: the members run in float32, whose likelihoods at a track's first scans carry 1e-3 of rounding
    np.testing.assert_allclose(out[keys.MEMBER_PROBS].numpy()[seen], ref[seen], rtol=0, atol=1e-3)
    fused = (out[keys.MEMBER_PROBS][..., None] * x.nan_to_num()).sum(-2)
    torch.testing.assert_close(out[keys.STATE][torch.from_numpy(seen)], fused[torch.from_numpy(seen)], rtol=0,
                               atol=1e-2)  # a member's float32 estimate on a subset of the rows: mm of rounding
    got = np.zeros((T, K), dtype=int)
    for k, name in enumerate(bank.names):
        got[: len(rows[name]), k] = rows[name]
    np.testing.assert_array_equal(got, runs)
    assert runs[-1].sum() < B * K and (runs[-1] > 0).any()  # some member was pruned, and the tracks go on
    if after:  # the early prunings wait: at scan 12 after the first detection no member has left yet
        assert (runs[: min(first) + after] == B).all()
    else:
        assert (runs[: min(first) + 12] < B).any()
    assert (out[keys.MEMBER_PROBS].numpy()[seen][ref[seen] == 0] == 0).all()  # a pruned member weighs nothing


def test_pruning_that_removes_nothing_is_the_bank_to_the_bit(tracks):
    """The shipped bank with a prune below every member probability the tracks reach (scan by scan, ``step``) gives
    the unpruned bank's estimate, covariance, mode and member probabilities to the bit."""
    bank = NetworkBank.from_names(prune=0.0)
    iv = torch.ones(tracks.shape[:2], dtype=torch.float64)
    ref = bank.track(tracks, intervals=iv, return_cov=True)
    w = ref[keys.MEMBER_PROBS]
    low = float(w[w > 0].min())
    assert low > 1e-300
    bank.prune = low / 2
    got = bank.track(tracks, intervals=iv, return_cov=True)
    for key in (keys.STATE, keys.STATE_COV, keys.MODE_PROBS, keys.MEMBER_PROBS):
        torch.testing.assert_close(got[key], ref[key], equal_nan=True, rtol=0, atol=0)


def test_the_general_network_gives_way_to_the_3dlast_network(tracks):
    """The shipped bank (``DEFER``): on 1 s tracks, which the 3D-LAST network takes, the general network runs on no
    row and has no weight, and the bank is the bank without it (to 1e-9 m: the same members and weights, a prior of
    1/6 in place of 1/5 rounding otherwise); on 5 s tracks it runs as before, the bank the same to the bit as one that
    defers nothing."""
    assert DEFER == {"general": ("3dlast",)}
    td5 = generate(2, seed=4, spec=DataSpec(T=80, min_segment=20, dt=5.0))
    z = torch.cat([tracks, td5[keys.MEASUREMENTS].double()])
    iv = torch.cat([torch.ones(6, 80), torch.full((2, 80), 5.0)]).double()
    bank = NetworkBank.from_names(prune=0.0)
    assert bank.defer == {"general": ("3dlast",)}
    rows = _counting(bank)
    out = bank.track(z, intervals=iv, return_cov=True)
    assert set(rows["general"]) == {2}  # the two 5 s tracks only
    assert (out[keys.MEMBER_PROBS][:6, :, 0].nan_to_num() == 0).all()
    without = NetworkBank.from_names(["real", "real-5s", "real-11s", "real-4.5-12s", "3dlast"], prune=0.0)
    alone = without.track(tracks, intervals=iv[:6], return_cov=True)
    torch.testing.assert_close(out[keys.STATE][:6], alone[keys.STATE], equal_nan=True, rtol=0, atol=1e-9)
    every = NetworkBank.from_names(prune=0.0, defer={})
    five = every.track(z[6:], intervals=iv[6:], return_cov=True)  # each member on the same rows as in ``out``
    for key in (keys.STATE, keys.STATE_COV, keys.MEMBER_PROBS):
        torch.testing.assert_close(out[key][6:], five[key], equal_nan=True, rtol=0, atol=0)
    one = every.track(tracks, intervals=iv[:6])
    assert (one[keys.MEMBER_PROBS][:, 5:, 0] > 0).all()  # without deferring, general is in the 1 s tracks


def test_the_shipped_bank_prunes_and_defers():
    """``immnet track``'s and ``immnet evaluate``'s bank (``BankMethod()``) and ``NetworkBank.from_names()`` prune at
    ``PRUNE`` and defer as ``DEFER``; a bank of one's own members keeps the pairs of ``DEFER`` among them."""
    assert 0 < PRUNE < 0.01 and PRUNE_AFTER > 0
    for bank in (BankMethod().net, NetworkBank.from_names()):
        assert bank.prune == PRUNE and bank.defer == DEFER and bank.prune_after == PRUNE_AFTER
    assert NetworkBank.from_names(["general", "real"]).defer == {}


def test_prune_and_defer_are_checked_by_name():
    from immnet.filters.methods import build_method

    net = build_method("imm-tuned").network().float()
    for bad in (-0.1, 1.0, float("nan"), True, "0.01"):
        with pytest.raises(ValueError, match=r"a bank's prune is a probability in \[0, 1\), got"):
            NetworkBank({"a": net}, prune=bad)
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match=r"a bank's prune_after is a whole number of scans, 0 or more, got"):
            NetworkBank({"a": net}, prune_after=bad)
    nets = {"a": net, "b": build_method("imm-min").network().float(), "c": net}
    with pytest.raises(ValueError, match=r"a bank's defer names d, not a member \(a, b, c\)"):
        NetworkBank(nets, defer={"a": ["d"]})
    with pytest.raises(ValueError, match=r"a bank's member 'a' gives way to other members, one or more, got \['a'\]"):
        NetworkBank(nets, defer={"a": ["a"]})
    with pytest.raises(ValueError, match=r"bank member 'b' both gives way \(defer\) and is given way to"):
        NetworkBank(nets, defer={"a": ["b"], "b": ["c"]})
    with pytest.raises(ValueError, match=r"a bank's defer maps a member to the members it gives way to, got"):
        NetworkBank(nets, defer=["a", "b"])


def test_the_fallback_is_never_pruned():
    """The general network, which gives way to the 3D-LAST network (``DEFER``), is the bank's member for any
    interval: at a prior of 0.001 against 1 for each other member, pruned at 0.01 from the first scan, 5 s tracks keep
    it, so that in streaming a track scanned every 5 s and then every second goes on with it (the 5 s networks cannot
    take 1 s scans) where a bank that pruned it refuses the scan."""
    prior = [0.001, 1, 1, 1, 1, 1]
    td = generate(4, seed=8, spec=DataSpec(T=30, min_segment=10, dt=5.0))
    z = td[keys.MEASUREMENTS].double()
    iv = torch.full(z.shape[:2], 5.0, dtype=torch.float64)
    bank = NetworkBank.from_names(prior=prior, prune=0.01, prune_after=0)
    w = bank.track(z, intervals=iv)[keys.MEMBER_PROBS]
    seen = ~torch.isnan(w[..., 0])
    assert (w[..., 0][seen] > 0).all()
    bank.reset(4)
    for t in range(30):
        out = bank.step(z[:, t], dt=5.0 if t < 20 else 1.0)
        if t >= 20:  # the 1 s scans: only the general network takes them
            torch.testing.assert_close(out[keys.MEMBER_PROBS][:, 0], torch.ones(4, dtype=torch.float64), rtol=0, atol=0)
    unguarded = NetworkBank.from_names(prior=prior, prune=0.01, prune_after=0, defer={})  # general may be pruned
    assert (unguarded.track(z, intervals=iv)[keys.MEMBER_PROBS][:, -1, 0] == 0).all()
    unguarded.reset(4)
    with pytest.raises(ValueError, match=r"no member of this bank still in track\(s\) .* takes a scan after 1 s"):
        for t in range(30):
            unguarded.step(z[:, t], dt=5.0 if t < 20 else 1.0)
