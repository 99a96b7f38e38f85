"""The streaming Python API (``Tracker`` and ``NetworkBank``: ``reset``, ``step``, ``track``) refuses bad input with one
line naming what is wrong, before anything of the tracker's state changes."""

import math

import numpy as np
import pytest
import torch

from immnet import keys
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.data.times import scan_intervals
from immnet.tracking.bank import NetworkBank
from immnet.tracking.tracker import Tracker


@pytest.fixture(scope="module")
def z():
    return generate(3, seed=5, spec=DataSpec(T=30, min_segment=10))[keys.MEASUREMENTS].float()


@pytest.fixture(scope="module")
def general():
    return Tracker.pretrained("general")


@pytest.fixture(scope="module")
def bank():
    return NetworkBank.from_names()  # the shipped bank, Tracker.pretrained()'s


def _state(tracker):
    """Everything a step may change, copied."""
    if isinstance(tracker, NetworkBank):
        carry = {name: c.clone() for name, c in tracker.carries.items()}
        return carry, tracker.log_w.clone(), tracker.fresh.clone(), tracker.n_gated
    return tracker.carry.clone(), tracker.fresh.clone(), tracker.n_gated


def _same(a, b) -> bool:
    """Two ``_state``s equal to the bit (NaN where NaN)."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, torch.Tensor):
        return torch.equal(a.isnan(), b.isnan()) and torch.equal(a.nan_to_num(), b.nan_to_num())
    if hasattr(a, "to_dict"):
        return _same(a.to_dict(), b.to_dict())
    return a == b


def _started(tracker, z, n=5):
    tracker.reset(z.shape[0])
    for t in range(n):
        tracker.step(z[:, t], dt=1.0)
    return _state(tracker)


@pytest.mark.parametrize("which", ["general", "bank"])
def test_a_nan_interval_is_refused_before_anything_changes(which, request, z):
    """``step(dt=nan)``, a NaN among a step's intervals and a NaN in ``track``'s intervals are refused, naming where,
    as dt inf (no time to coast through), 0 and -1 (no interval a network was trained at) are; the tracker's carry, fresh flags and gated count are as before, and it runs on."""
    tracker = request.getfixturevalue(which)
    before = _started(tracker, z)
    with pytest.raises(ValueError, match=r"^dt is nan at track 0: the time since a track.s previous scan is a number"):
        tracker.step(z[:, 5], dt=float("nan"))
    with pytest.raises(ValueError, match=r"^dt is nan at track 1:"):
        tracker.step(z[:, 5], dt=[1.0, float("nan"), 1.0])
    with pytest.raises(ValueError, match=r"^dt is inf at track 0:"):
        tracker.step(z[:, 5], dt=math.inf)
    for bad in (0.0, -1.0):
        with pytest.raises(ValueError, match="trained|no member"):
            tracker.step(z[:, 5], dt=bad)
    assert _same(_state(tracker), before)
    iv = torch.ones(z.shape[:2], dtype=torch.float64)
    iv[2, 7] = float("nan")
    with pytest.raises(ValueError, match=r"^intervals is nan at track 2, scan 7:"):
        tracker.track(z, intervals=iv)
    assert _same(_state(tracker), before)
    out = tracker.step(z[:, 5], dt=1.0)
    assert torch.isfinite(out[keys.FUSED]).all()


@pytest.mark.parametrize("which", ["general", "bank"])
def test_a_scan_of_another_number_of_tracks_is_refused(which, request, z):
    """After ``reset(3)`` a scan of 2 rows is refused, naming both numbers, and the three tracks run on as if it had
    not come (their velocities not back to 0); a first scan without a reset sizes the tracker."""
    tracker = request.getfixturevalue(which)
    before = _started(tracker, z)
    with pytest.raises(ValueError, match=r"^this tracker holds 3 tracks but the scan has 2 rows: give one row per "
                                         r"track \(NaN for a missed detection\), or reset\(2\) first$"):
        tracker.step(z[:2, 5], dt=1.0)
    assert _same(_state(tracker), before)
    torch.testing.assert_close(tracker.step(z[:, 5], dt=1.0)[keys.FUSED], _replay(tracker, z, 6)[keys.FUSED],
                               rtol=0, atol=0)
    fresh = Tracker.pretrained("general") if which == "general" else NetworkBank.from_names(["general"])
    fresh.step(z[:2, 0])  # no reset: the first scan sizes it
    with pytest.raises(ValueError, match="holds 2 tracks but the scan has 3 rows"):
        fresh.step(z[:, 1])


def _replay(tracker, z, n):
    """The tracker's output at scan ``n - 1`` of ``z`` at 1 s, run again from a reset."""
    tracker.reset(z.shape[0])
    for t in range(n):
        out = tracker.step(z[:, t], dt=1.0)
    return out


@pytest.mark.parametrize("which", ["general", "bank"])
def test_bad_numbers_of_tracks_lengths_and_kinds_of_measurement_are_refused(which, request, z):
    """``reset`` of a negative, fractional or boolean number of tracks; ``track`` of no track or no scan; a dt list
    (or reset mask) of another length than the scan's, naming both; boolean or complex measurements, in ``step`` and
    ``track``: one ValueError each, the tracker as before."""
    tracker = request.getfixturevalue(which)
    before = _started(tracker, z)
    for n in (-1, 0, 2.5, True, "3"):
        with pytest.raises(ValueError, match=r"^reset\(n_tracks\) takes a whole number of tracks, at least 1, got "):
            tracker.reset(n)
    with pytest.raises(ValueError, match=r"^measurements are \[n_tracks, T, 3\] with at least one track and one "
                                         r"scan, got \(0, 30, 3\)$"):
        tracker.track(z[:0])
    with pytest.raises(ValueError, match=r"got \(3, 0, 3\)$"):
        tracker.track(z[:, :0])
    with pytest.raises(ValueError, match=r"^dt has 2 values for 3 tracks: give one, or one per track$"):
        tracker.step(z[:, 5], dt=[1.0, 1.0])
    with pytest.raises(ValueError, match=r"^reset has 2 values for 3 tracks"):
        tracker.step(z[:, 5], reset=[True, False])
    for kind, bad in (("bool", z[:, 5] > 0), ("complex64", z[:, 5].to(torch.complex64)),
                      ("bool", np.ones((3, 3), dtype=bool))):
        with pytest.raises(ValueError, match=rf"^measurements are real numbers of metres, got {kind}$"):
            tracker.step(bad)
    with pytest.raises(ValueError, match=r"^measurements are real numbers of metres, got complex128$"):
        tracker.track(z.numpy().astype(np.complex128))
    assert _same(_state(tracker), before)
    tracker.reset(np.int64(2))  # a whole number of any integer type
    assert tracker.step(z[:2, 0])[keys.FUSED].shape == (2, 9)


def test_a_tracker_says_what_it_is():
    """``print(Tracker.pretrained())`` (the bank) names each member, the scan intervals it serves and where its
    provenance is; ``print(Tracker.pretrained("real"))`` the network, its interval and provenance; neither an object
    address. Each provenance named is a file shipped in the package."""
    from immnet.checkpoints import PRETRAINED
    from immnet.tracking.bank import DEFAULT_MEMBERS

    bank = repr(Tracker.pretrained())
    assert " at 0x" not in bank and "PROVENANCE-bank.md" in bank.splitlines()[0]
    bands = {"general": "0.5-12 s", "real": "1 s", "real-5s": "4.5-5.5 s", "real-11s": "10-12 s",
             "real-4.5-12s": "4.5-12 s", "3dlast": "1 s"}
    files = {name: f"PROVENANCE-{name}.md" for name in bands} | {"3dlast": "PROVENANCE.md"}
    lines = bank.splitlines()[1:]
    assert [line.split()[0] for line in lines] == list(DEFAULT_MEMBERS)
    for line in lines:
        name = line.split()[0]
        assert f"scans of {bands[name]} " in line and line.rstrip(")").endswith(f"immnet/pretrained/{files[name]}")
        assert (PRETRAINED.parent / files[name]).is_file()
    real = repr(Tracker.pretrained("real"))
    assert real == "Tracker(real: scans of 1 s, no range guard; provenance immnet/pretrained/PROVENANCE-real.md)"
    assert "range guard;" in repr(Tracker.pretrained("3dlast")).replace("no range guard", "")


@pytest.mark.parametrize("which", ["general", "bank"])
def test_a_long_interval_restarts_the_track_in_step_and_track_alike(which, request, z):
    """An interval past the coasting limit (``max_coast``, 30 s, the CSV path's ``--max-coast``) restarts the track
    there instead of coasting through it scan by scan (dt 1e9 would run for ever): ``step(z, dt=1e9)`` gives what a
    fresh tracker's first step gives on that scan (at the interval of the scan before), the other tracks run on; and
    ``step`` over sequences with a huge gap, a 45 s gap and 31 s without a detection (31 missed scans) gives ``track``'s
    numbers for them (to float32 rounding: the restarted parts run as batches of their own)."""
    tracker = request.getfixturevalue(which)
    fresh = Tracker.pretrained("general") if which == "general" else NetworkBank.from_names()
    _started(tracker, z, 10)
    got = tracker.step(z[:, 10], dt=torch.tensor([1e9, 1.0, 1.0], dtype=torch.float64))
    fresh.reset(1)
    alone = fresh.step(z[:1, 10], dt=1.0)
    torch.testing.assert_close(got[keys.FUSED][0], alone[keys.FUSED][0], rtol=0, atol=0)
    vel = [1, 4, 7]  # the state is [x, vx, ax, y, vy, ay, z, vz, az]
    assert torch.isfinite(got[keys.FUSED][1:]).all() and got[keys.FUSED][1:, vel].ne(0).all()  # the others run on
    assert got[keys.FUSED][0, vel].eq(0).all()  # a first detection: no velocity yet
    zz = torch.cat([z, z[:, :10]], 1)  # 40 scans at 1 s but for the gaps
    iv = torch.ones(zz.shape[:2], dtype=torch.float64)
    iv[0, 12], iv[1, 20] = 1e9, 45.0
    zz[2, 4:35] = float("nan")  # no detection after scan 3: 30 s by scan 33 (coasting), 31 s by scan 34 (restarted)
    ref = tracker.track(zz, intervals=iv, return_cov=True)
    tracker.reset(3)
    outs = [tracker.step(zz[:, t], dt=iv[:, t]) for t in range(zz.shape[1])]
    st = torch.stack([o[keys.FUSED] for o in outs], 1)
    # a batch's composition alone moves float32 numbers by ~1e-3 over 20 scans (track 0 of zz[:, 12:] tracked in a
    # batch of 3 and alone: 0.32 apart by the general network, 1.03 by the bank): the structure is checked exactly below
    torch.testing.assert_close(st, ref[keys.STATE], equal_nan=True, rtol=5e-3, atol=2.0)
    if which == "general":  # the bank's covariance adds its members' spread, which the rounding of weights moves more
        torch.testing.assert_close(torch.stack([o[keys.FUSED_COV] for o in outs], 1), ref[keys.STATE_COV],
                                   equal_nan=True, rtol=5e-3, atol=1.0)
    else:
        torch.testing.assert_close(torch.stack([o[keys.MEMBER_PROBS] for o in outs], 1), ref[keys.MEMBER_PROBS],
                                   equal_nan=True, rtol=0, atol=2e-2)
    assert torch.equal(st.isnan(), ref[keys.STATE].isnan())
    for b, t in ((0, 12), (1, 20), (2, 35)):  # each restart's first detection: no velocity, as a fresh track's
        assert st[b, t].isfinite().all() and st[b, t, vel].eq(0).all() and st[b, t + 1, vel].ne(0).all()
    assert st[2, 33].isfinite().all() and st[2, 34].isnan().all()  # coasting at 30 s; restarted, no detection yet
    assert st[:2, 12:20].isfinite().all() and st[:2, [11, 19]][:, :, vel].ne(0).all()


@pytest.mark.parametrize("which", ["immnet", "immnet-bank"])
def test_evaluate_scores_a_window_as_one_track_through_a_long_stretch_without_detection(which):
    """``immnet evaluate`` scores each data window as one track: its methods have no coasting limit
    (``max_coast=inf``), so a track with 40 s without a detection (40 missed scans at 1 s) coasts through them, as a
    tracker with no limit, and keeps its velocity after them, where the streaming API's 30 s would restart it."""
    from immnet.filters.methods import build_method
    from immnet.tracking.methods import IMMNetMethod

    batch = generate(2, seed=7, spec=DataSpec(T=70, min_segment=10))
    batch[keys.MEASUREMENTS][0, 15:55] = float("nan")  # scans 15-54 missed: 41 s from scan 14's detection to 55's
    method = build_method(which)
    assert math.isinf(method.net.max_coast if which == "immnet-bank" else method.tracker.max_coast)
    got = method.track(batch)[keys.STATE]
    z, iv = batch[keys.MEASUREMENTS], scan_intervals(batch)
    if which == "immnet":
        assert isinstance(method, IMMNetMethod)
        ref = Tracker(method.net, max_coast=math.inf).track(z, 500, method.net.intervals_for(batch))[keys.STATE]
    else:
        net = method.net
        bank = NetworkBank(net.members, max_coast=math.inf, prune=net.prune, defer=net.defer, prune_after=net.prune_after)
        ref = bank.track(z, 500, iv)[keys.STATE]
    torch.testing.assert_close(got, ref.double(), rtol=0, atol=0, equal_nan=True)
    vel = [1, 4, 7]
    assert got[0, 55:].isfinite().all() and got[0, 55, vel].ne(0).all()  # coasted through: it has a velocity


def test_a_network_off_the_cpu_is_refused_where_the_tracker_is_built():
    """The trackers keep each track's frame, intervals and coasting on the CPU: a network on another device (here
    the meta device, which holds no data) is refused in one line naming it, before any scan (it failed inside the
    first scan, with torch's message)."""
    from immnet.checkpoints import shipped
    from immnet.tracking.networks import load_network

    net = load_network(shipped("real")).to("meta")
    with pytest.raises(ValueError, match="a Tracker runs on the CPU; this network is on meta"):
        Tracker(net)
    with pytest.raises(ValueError, match=r"member 'real'\) runs on the CPU; this network is on meta"):
        NetworkBank({"real": net})
    Tracker(net.to_empty(device="cpu"))  # on the CPU again: taken
