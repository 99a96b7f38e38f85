"""Issue 22, item 4: ``immnet track`` and the Python API at any scan interval (CSV times to 0.01 s, epoch
times): an estimate for every row, below the raw measurements' error."""

import csv

import numpy as np
import pytest
import torch

from immnet import keys
from immnet.cli import main
from immnet.filters.methods import build_method
from immnet.tracking.methods import check_dt
from immnet.tracking.segments import split_rows, track_rows

EPOCH = 1_733_070_000.0


def _truth(t):
    """A closed-form track: 60 s at 150 m/s along x, then a 3 deg/s turn (constant speed), level at 3 km."""
    v, w, t1 = 150.0, np.deg2rad(3.0), 60.0
    x = np.where(t < t1, 10_000 + v * t, 10_000 + v * t1 + v / w * np.sin(w * (t - t1)))
    y = np.where(t < t1, 5_000.0, 5_000 + v / w * (1 - np.cos(w * (t - t1))))
    return np.stack([x, y, np.full_like(t, 3_000.0)], -1)


@pytest.fixture(scope="module")
def irregular(tmp_path_factory):
    rng = np.random.default_rng(22)
    rows, truth = [], []
    for tid in ("a", "b"):
        dt = np.round(rng.uniform(4.5, 5.5, 40), 2)
        t = np.round(np.cumsum(dt) - dt[0] + (0 if tid == "a" else 7.31), 2)
        p = _truth(t)
        z = p + rng.normal(0, 5.0, p.shape)
        rows += [[tid, f"{EPOCH + tk:.2f}", *(repr(float(v)) for v in zk)] for tk, zk in zip(t, z)]
        truth.append(p)
    path = tmp_path_factory.mktemp("irr") / "in.csv"
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["track_id", "t", "x", "y", "z"])
        w.writerows(rows)
    return path, rows, np.concatenate(truth)


def _tracked_below_the_raw_error(irregular, tmp_path, *options):
    """``immnet track`` of the irregular CSV: every row's time kept and estimated, the position RMSE below the raw
    measurements'; returns the estimates ``[R, 3]``."""
    path, rows, truth = irregular
    out = tmp_path / "out.csv"
    assert main(["track", "--input", str(path), "--output", str(out), *options]) == 0
    with open(out, newline="") as f:
        got = list(csv.DictReader(f))
    assert [r["t"] for r in got] == [r[1] for r in rows]
    est = np.array([[float(r[c]) for c in ("x", "y", "z")] for r in got])
    assert np.isfinite(est).all()
    raw = np.array([[float(v) for v in r[2:]] for r in rows])
    rmse = lambda e: float(np.sqrt(((e - truth) ** 2).sum(-1).mean()))  # noqa: E731
    assert rmse(est) < rmse(raw), (rmse(est), rmse(raw))
    return est


def test_track_at_irregular_epoch_times_estimates_every_row_below_the_raw_error(irregular, tmp_path):
    """Needs the filters branch (model-based IMMs reading ``t``): without it the IMM runs as if scans were
    1 s apart and its error is far above the raw measurements'."""
    path, rows, truth = irregular
    est = _tracked_below_the_raw_error(irregular, tmp_path, "--method", "imm-tuned")
    # the Python API: the same segments through Method.track with t gives the same numbers
    from immnet.data.csvio import read_tracks_csv

    tracks = read_tracks_csv(path)
    segs, offset = split_rows(tracks.ids, tracks.t, tracks.z)
    state, _ = track_rows(build_method("imm-tuned"), segs, offset)
    np.testing.assert_allclose(est, state[:, [0, 3, 6]], rtol=0, atol=1e-6)


def test_the_default_weights_track_irregular_epoch_times_below_the_raw_error(irregular, tmp_path):
    """The shipped default (the general network, 0.5-12 s) takes the CSV's own times: an estimate for every row,
    below the raw measurements' error; the streaming API fed each row's interval gives the same numbers."""
    from immnet.tracking import Tracker

    path, rows, truth = irregular
    est = _tracked_below_the_raw_error(irregular, tmp_path)  # 40 scans from the start, a 3 deg/s turn at 5 s scans
    tracker = Tracker.pretrained()
    for tid in ("a", "b"):
        mine = [i for i, r in enumerate(rows) if r[0] == tid]
        t = np.array([float(rows[i][1]) - EPOCH for i in mine])
        z = torch.tensor([[float(v) for v in rows[i][2:]] for i in mine], dtype=torch.float32)
        tracker.reset(1)
        gaps = np.diff(t)
        dts = np.r_[np.median(gaps), gaps]  # the CLI's first interval: the track's median spacing
        api = torch.stack([tracker.step(z[k][None], dt=float(dts[k]))[keys.FUSED][0] for k in range(len(mine))])
        # float32 through both, two tracks a batch in the CLI and one here: equal to a few float32 roundings
        # (an ulp is 1.2e-7 of a coordinate, 0.002 m at 20 km)
        np.testing.assert_allclose(est[mine], api[:, [0, 3, 6]].double().numpy(), rtol=5e-7, atol=0)


@pytest.mark.parametrize("times", ["dt", "t"])
def test_an_npz_at_5s_scans_is_tracked_at_its_own_intervals(irregular, tmp_path, times):
    """``immnet track`` of an .npz with the default (the bank; its general network trained at 0.5-12 s, nominal 1 s): a uniform ``dt = 5``
    or per-scan times ``t`` (4.5-5.5 s) are the intervals each scan is tracked at, as ``Tracker.track`` fed them; the
    position error below the raw measurements' (run at 1 s a step, the velocity is five times the truth's and the
    estimates lag by kilometres), the output's ``dt`` the input's."""
    from immnet.tracking import Tracker

    path, rows, truth = irregular
    mine = [i for i, r in enumerate(rows) if r[0] == "a"]
    t = np.array([float(rows[i][1]) - EPOCH for i in mine])
    if times == "dt":
        t = 5.0 * np.arange(len(mine))
    p = _truth(t)
    z = (p + np.random.default_rng(5).normal(0, 5.0, p.shape))[None].astype(np.float32)
    extra = {"dt": 5.0} if times == "dt" else {"t": t[None]}
    np.savez(tmp_path / "in.npz", measurements=z, **extra)
    assert main(["track", "--input", str(tmp_path / "in.npz"), "--output", str(tmp_path / "out.npz")]) == 0
    out = np.load(tmp_path / "out.npz")
    est = out["state"][0][:, [0, 3, 6]]
    rmse = lambda e: float(np.sqrt(((e - p)[5:] ** 2).sum(-1).mean()))  # noqa: E731
    assert rmse(est) < rmse(z[0]), (rmse(est), rmse(z[0]))
    gaps = np.diff(t)
    speed = np.linalg.norm(out["state"][0][10:, [1, 4, 7]], axis=-1)
    np.testing.assert_allclose(speed, 150.0, rtol=0.1)  # the truth's speed, 150 m/s, in and after the turn
    intervals = torch.tensor(np.r_[np.median(gaps), gaps][None], dtype=torch.float32)
    api = Tracker.pretrained().track(torch.from_numpy(z), intervals=intervals)
    np.testing.assert_allclose(out["state"], api["state"].numpy(), rtol=1e-5, atol=1e-3)
    assert float(out["dt"]) == (5.0 if times == "dt" else float(np.median(gaps)))


@pytest.mark.parametrize("times", ["t", "dt"])
def test_an_npz_gap_beyond_the_networks_range_is_coasted_as_a_csvs_is(tmp_path, times):
    """``immnet track`` of an .npz whose scans are further apart than the general network's 12 s: each long gap cut
    into missed scans inside the range, as the CSV path cuts it (``track_rows(max_interval=...)``), the input's
    scans written back. Per-scan times with a 20 s and a 26 s gap give the CSV path's estimates of the same rows;
    uniform 20 s scans give ``Tracker.track`` of the 10 s grid with every other scan missed."""
    from immnet.tracking import Tracker

    if times == "t":
        t = np.r_[np.arange(0.0, 50.0, 5.0), 70.0 + np.arange(0.0, 30.0, 5.0), 121.0 + np.arange(0.0, 40.0, 5.0)]
    else:
        t = 20.0 * np.arange(30)
    p = np.stack([10_000 + 150.0 * t, np.full_like(t, 5_000.0), np.full_like(t, 3_000.0)], -1)  # straight and level
    z = (p + np.random.default_rng(8).normal(0, 5.0, (len(t), 3))).astype(np.float32)
    z[3] = np.nan  # a missed scan of the input's own
    extra = {"t": t[None]} if times == "t" else {"dt": 20.0}
    np.savez(tmp_path / "in.npz", measurements=z[None], **extra)
    assert main(["track", "--input", str(tmp_path / "in.npz"), "--output", str(tmp_path / "out.npz")]) == 0
    out = np.load(tmp_path / "out.npz")
    assert out["state"].shape == (1, len(t), 9) and out["state_cov"].shape == (1, len(t), 9, 9)
    assert float(out["dt"]) == (5.0 if times == "t" else 20.0)
    if times == "t":
        with open(tmp_path / "in.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["track_id", "t", "x", "y", "z"])
            for tk, zk in zip(t, z):
                w.writerow(["a", f"{tk:.2f}", *("" if np.isnan(v) else repr(float(v)) for v in zk)])
        assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(tmp_path / "out.csv")]) == 0
        with open(tmp_path / "out.csv") as f:
            csv_rows = list(csv.DictReader(f))
        csv_pos = np.array([[float(r[c]) for c in ("x", "y", "z")] for r in csv_rows])
        np.testing.assert_allclose(out["state"][0][:, [0, 3, 6]], csv_pos, rtol=0, atol=1e-3)
    else:
        grid = np.full((1, 2 * len(t) - 1, 3), np.nan, dtype=np.float32)
        grid[0, ::2] = z
        api = Tracker.pretrained().track(torch.from_numpy(grid), intervals=torch.full((1, grid.shape[1]), 10.0))
        np.testing.assert_allclose(out["state"][0], api["state"][0, ::2].numpy(), rtol=1e-5, atol=1e-3)
    # tracked through the gaps, not lost in them: positions about as good as the raw measurements' (at 20 s a
    # maneuver-ready network leans on them), the velocity, which no scan measures, the truth's 150 m/s east
    ok = ~np.isnan(z[:, 0])
    err = np.sqrt(((out["state"][0][:, [0, 3, 6]] - p)[ok][3:] ** 2).sum(-1).mean())
    assert err < 1.1 * np.sqrt(((z - p)[ok][3:] ** 2).sum(-1).mean())
    # at 20 s scans the missed scan 3 leaves 40 s without a detection, past the coasting limit (30 s, as the CSV
    # path's): the track restarts at scan 4, its velocity from scan 5 on
    first = 5 if times == "dt" else 4
    np.testing.assert_allclose(out["state"][0][first:, 1], 150.0, rtol=0.1)
    np.testing.assert_allclose(out["state"][0][first:, [4, 7]], 0.0, atol=15.0)


def test_tracker_coasts_a_long_gap_in_track_and_step_and_refuses_intervals_it_was_not_trained_at():
    """``Tracker.track(z, intervals=...)``: for the general weights (0.5-12 s) a 20 s interval is two 10 s scans, the
    first missed, and the output holds the scans given (equal to the 10 s grid tracked outright; ``Tracker.step``
    coasts it as well, to the same numbers); an interval below the range, or for the 1 s benchmark network any
    interval but 1 s, is refused by name, by ``track`` and ``step`` alike (it ran, extrapolated, before)."""
    from immnet.tracking import Tracker

    t = np.r_[0.0, 5.0, 10.0, 30.0, 35.0, 40.0, 60.0, 65.0]
    p = np.stack([10_000 + 150.0 * t, np.full_like(t, 5_000.0), np.full_like(t, 3_000.0)], -1)
    z = torch.from_numpy((p + np.random.default_rng(3).normal(0, 5.0, p.shape)).astype(np.float32))[None]
    intervals = torch.from_numpy(np.r_[5.0, np.diff(t)])[None]
    tracker = Tracker.pretrained("general")
    out = tracker.track(z, intervals=intervals, return_cov=True)
    assert tuple(out["state"].shape) == (1, 8, 9) and tuple(out["state_cov"].shape) == (1, 8, 9, 9)
    grid = torch.full((1, 10, 3), float("nan"))
    keep = [0, 1, 2, 4, 5, 6, 8, 9]  # 10 -> 30 s and 40 -> 60 s each two scans of 10 s
    grid[0, keep] = z[0]
    steps = torch.tensor([[5.0, 5.0, 5.0, 10.0, 10.0, 5.0, 5.0, 10.0, 10.0, 5.0]])
    ref = Tracker.pretrained("general").track(grid, intervals=steps, return_cov=True)
    for key in ("state", "mode_probs", "state_cov"):
        torch.testing.assert_close(out[key], ref[key][:, keep], rtol=1e-5, atol=1e-4)
    # streaming: the same numbers, the 20 s intervals coasted in the step (a track's first scan's interval is nominal)
    stream = Tracker.pretrained("general")
    stream.reset(1)
    steps = [stream.step(z[:, k], dt=float(intervals[0, k]) if k else 25.0) for k in range(8)]
    for key, name in ((("fused", "state"), "state"), (("fused", "cov"), "state_cov"), ("mode_probs", "mode_probs")):
        torch.testing.assert_close(torch.stack([o[key] for o in steps], 1), out[name], rtol=1e-5, atol=1e-4)
    kept, gated = stream.carry.clone(), stream.n_gated
    with pytest.raises(ValueError, match="trained on intervals 0.5-12 s but this data has an interval of 0.2 s"):
        stream.step(torch.full((1, 3), 1e9), reset=torch.tensor([True]), dt=0.2)  # refused: nothing changes
    assert stream.n_gated == gated
    torch.testing.assert_close(stream.carry.to_dict(), kept.to_dict(), equal_nan=True, rtol=0, atol=0)
    with pytest.raises(ValueError, match="trained on intervals 0.5-12 s but this data has an interval of 0.2 s"):
        tracker.track(z, intervals=torch.full((1, 8), 0.2))
    with pytest.raises(ValueError, match=r"intervals are \[n_tracks, T\]"):
        tracker.track(z, intervals=torch.full((1, 7), 5.0))
    with pytest.raises(ValueError, match="sampled at dt = 1 s but this data has dt = 2 s"):
        Tracker.pretrained("3dlast").track(z, intervals=torch.full((1, 8), 2.0))
    one = Tracker.pretrained("3dlast")
    # its own interval is taken (the step's interval path: float32 roundoff of the fixed-interval one)
    torch.testing.assert_close(one.track(z, intervals=torch.ones(1, 8))["state"], one.track(z)["state"], rtol=1e-4,
                               atol=1e-2)


def test_an_interval_a_hair_over_the_range_is_one_scan_and_scan_0_is_nominal():
    """An interval within ``check_dt``'s tolerance (1e-6) above a range's end is one scan the network takes, not two
    halves below its range, in ``track`` and ``step`` alike; a track's first interval longer than the range is taken as
    nominal even where no other interval is cut."""
    from immnet.tracking import Tracker
    from immnet.tracking.networks import coast_cuts
    from immnet.tracking.segments import _scan_times

    real5 = Tracker.pretrained("real-5s")
    hair = 5.5 * (1 + 5e-7)
    cuts, each = coast_cuts(real5.net, torch.tensor([hair, 11.0, 12.0], dtype=torch.float64))
    assert cuts.tolist() == [1, 2, 3] and each[0] == hair
    full, pos = _scan_times(np.array([0.0, hair, hair + 11.0]), 5.5)
    assert pos.tolist() == [0, 1, 3]
    z = torch.from_numpy(np.stack([np.arange(6) * 1000.0, np.full(6, 5e3), np.full(6, 3e3)], -1)).float()[None]
    out = real5.track(z, intervals=torch.tensor([[30.0, 5.0, hair, 11.0, 5.0, 5.0]], dtype=torch.float64))
    assert torch.isfinite(out["state"][0, 1:]).all()
    nominal = real5.track(z, intervals=torch.tensor([[30.0, 5.0, 5.0, 5.0, 5.0, 5.0]]))  # nothing cut: scan 0 clamped
    assert torch.isfinite(nominal["state"][0, 1:]).all()
    real5.reset(1)
    steps = [real5.step(z[:, k], dt=float(v)) for k, v in enumerate([30.0, 5.0, hair, 11.0, 5.0, 5.0])]
    torch.testing.assert_close(torch.stack([o["fused", "state"] for o in steps], 1), out["state"], rtol=1e-5, atol=1e-3)


def test_a_gap_beyond_the_networks_range_is_coasted_at_intervals_inside_it():
    """``track_rows(max_interval=...)``: rows 20 s apart for a network trained up to 12 s are two 10 s scans, the
    one between them a missed detection; rows inside the range keep their own times."""
    from immnet.tracking.segments import _scan_times

    full, pos = _scan_times(np.array([0.0, 5.0, 25.0, 30.0, 42.0]), 12.0)
    np.testing.assert_allclose(full, [0.0, 5.0, 15.0, 25.0, 30.0, 42.0])
    assert pos.tolist() == [0, 1, 3, 4, 5]
    full, pos = _scan_times(np.array([0.0, 5.0, 25.0]), None)
    assert full.tolist() == [0.0, 5.0, 25.0] and pos.tolist() == [0, 1, 2]


def test_rows_keep_hundredths_at_epoch_times(irregular):
    """Offsets from each segment's first time are exact to 0.01 s at 1.7e9 s (taken from the decimals)."""
    from immnet.data.csvio import read_tracks_csv

    tracks = read_tracks_csv(irregular[0])
    segs, offset = split_rows(tracks.ids, tracks.t, tracks.z)
    assert len(segs.span) == 2 and (segs.segment >= 0).all()
    want = np.array([float(t - EPOCH) for t in map(float, tracks.times)])
    starts = {s: want[segs.segment == s][0] for s in range(2)}
    np.testing.assert_allclose(offset, want - np.array([starts[s] for s in segs.segment]), atol=1e-6)
    assert not np.allclose(np.diff(offset[segs.segment == 0]) % 1.0, 0.0)


def test_a_fixed_interval_checkpoint_refuses_off_grid_times_and_names_the_way_out(irregular, tmp_path, capsys):
    assert main(["track", "--input", str(irregular[0]), "--output", str(tmp_path / "o.csv"), "--weights", "3dlast",
                 "--guard", "none"]) == 2
    err = capsys.readouterr().err
    assert "is not a whole number of scans (dt = 1)" in err and "--method imm-tuned" in err
    assert not (tmp_path / "o.csv").exists()


class _Net:
    dt = 1.0


def test_check_dt_names_the_interval_and_the_range():
    net = _Net()
    check_dt(net, torch.tensor([1.0, 1.0]))
    with pytest.raises(ValueError, match=r"trained on data sampled at dt = 1 s but this data has dt = 5 s"):
        check_dt(net, torch.tensor([1.0, 5.0]))
    net.interval_range = (0.5, 12.0)
    check_dt(net, torch.tensor([0.5, 4.87, 12.0]))
    with pytest.raises(ValueError, match=r"trained on intervals 0.5-12 s but this data has an interval of 20 s"):
        check_dt(net, torch.tensor([5.0, 20.0]))

    class AnyInterval:
        any_interval = True

    check_dt(_Net(), torch.tensor([3.3]), method=AnyInterval())


def test_step_at_the_nominal_interval_equals_step_without_one():
    """``Tracker.step(z, dt=net.dt)`` is ``step(z)``; another interval with a fixed-interval network: an error
    naming it."""
    from immnet.data.generate import generate
    from immnet.data.spec import DataSpec
    from immnet.tracking import Tracker

    z = generate(2, seed=3, spec=DataSpec(T=12, min_segment=4))[keys.MEASUREMENTS].float()
    a, b = Tracker.pretrained("general", guard=None), Tracker.pretrained("general", guard=None)
    a.reset(2), b.reset(2)
    for k in range(12):
        torch.testing.assert_close(a.step(z[:, k])[keys.FUSED], b.step(z[:, k], dt=torch.full((2,), a.net.dt))[keys.FUSED])
    if getattr(a.net, "interval_range", None) is None:
        with pytest.raises(ValueError, match="this data has dt = 5 s"):
            a.step(z[:, 0], dt=5.0)


def test_rmse_by_interval_pools_each_bins_scored_scans():
    """``metrics.rmse_by_interval`` against the formula written out in numpy: per bin, each axis's sqrt of the mean
    squared error over the scored scans whose interval lies in it (the last bin closed), then the mean over axes."""
    from immnet.evaluation.metrics import rmse_by_interval

    rng = np.random.default_rng(5)
    err = rng.normal(0, 3, (6, 40, 3))
    dt = rng.uniform(0.5, 12, (6, 40))
    dt[0, 3] = 12.0  # on the last edge: in the last bin
    mask = rng.random((6, 40)) > 0.2
    edges = [0.5, 4, 8, 12]
    got = rmse_by_interval(torch.tensor(err), torch.tensor(dt), edges, torch.tensor(mask))
    for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        sel = mask & (dt >= lo) & ((dt <= hi) if i == 2 else (dt < hi))
        want = np.sqrt((err[sel] ** 2).mean(0)).mean()
        assert got[i] == pytest.approx(want, rel=1e-12)
    assert rmse_by_interval(torch.tensor(err), torch.tensor(dt), [20, 30])[0] is None  # no scan in the bin
    with pytest.raises(ValueError, match="increasing"):
        rmse_by_interval(torch.tensor(err), torch.tensor(dt), [4, 2])


def test_the_interval_note_names_the_filter_only_where_the_provenance_has_the_network_behind():
    from immnet.tracking.advice import interval_note, track_intervals

    prov = {"interval_bins": {"data": "D", "edges": [0.5, 6, 12], "network": "net", "filter": "flt",
                              "rmse": {"net": [3.0, 5.0], "flt": [4.0, 4.0]}}}
    note = interval_note(prov, [9.5, 10.0, 10.5, np.nan])
    assert "10-12" not in note and "6-12 s" in note and "1.25x flt" in note and "--method flt" in note
    assert interval_note(prov, [1.0, 1.0, 2.0]) is None  # the network ahead there
    assert interval_note(prov, [12.0]) is not None  # the last edge is in the last bin
    assert interval_note(prov, [20.0]) is None and interval_note(prov, []) is None  # outside the bins, no data
    assert interval_note({}, [10.0]) is None and interval_note(None, [10.0]) is None  # weights without bins
    np.testing.assert_allclose(track_intervals(["a", "b", "a", "b", "a"], ["0", "5", "10", "6.5", "30"]),
                               [10.0, 20.0, 1.5])


def _one_track_csv(path, t, seed: int, r: float):
    """A CSV of one track ``a`` measured at times ``t`` with noise ``r`` (m)."""
    p = _truth(t) + np.random.default_rng(seed).normal(0, r, (len(t), 3))
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["track_id", "t", "x", "y", "z"])
        w.writerows([["a", f"{tk:g}", *(f"{v:.3f}" for v in zk)] for tk, zk in zip(t, p)])
    return path


@pytest.mark.parametrize("weights", ["general", None])
@pytest.mark.parametrize("spacing", [1.0, 8.5, 10.0])
def test_immnet_track_says_what_the_general_weights_provenance_says_at_the_datas_interval(tmp_path, capsys, spacing,
                                                                                          weights):
    """At 8.5 s and 10 s scans the general network was measured behind its filter (the provenance's ``interval_bins``),
    at 1 s ahead of it: ``immnet track`` with the general weights, and with the bank (the default), prints the note
    exactly where the provenance has the network behind. The bank's note adds what the real-flight network it runs
    there, trained for those scans, measured on real flights against the same filter (real-4.5-12s at 8.5 s, real-11s
    at 10 s); the general weights name the network to try."""
    import json

    from immnet.checkpoints import provenance_file, shipped

    bins = json.loads(provenance_file(shipped("general")).read_text())["interval_bins"]
    k = next(i for i, (lo, hi) in enumerate(zip(bins["edges"][:-1], bins["edges"][1:])) if lo <= spacing < hi)
    behind = bins["rmse"][bins["network"]][k] > bins["rmse"][bins["filter"]][k]
    path = _one_track_csv(tmp_path / "in.csv", np.arange(12) * spacing, seed=3, r=5.0)
    args = ["track", "--input", str(path), "--output", str(tmp_path / "o.csv")] + (["--weights", weights] if weights else [])
    assert main(args) == 0
    err = capsys.readouterr().err
    bank = weights is None
    said_of = {8.5: ("real-4.5-12s", "quickstart-7s"), 10.0: ("real-11s", "quickstart-11s")}  # spacing -> member, set
    assert (f"--method {bins['filter']}" in err) == behind, err
    assert ("the bank's general network was" in err) == (behind and bank), err
    assert "(its one member at these scans)" not in err  # a real-flight network takes every interval of 4.5-12 s
    for at, (name, data) in said_of.items():
        said = (f"'{name}', which the bank runs beside it at these scans, tracked real flights ({data}) better than "
                f"{bins['filter']}")
        assert (said in err) == (bank and spacing == at), err
    assert ("--weights real-" in err) == (spacing != 1.0 and weights == "general"), err
    assert behind == (spacing >= 8.0)  # as measured (docs/results.md "The general model"): ahead at 1 s, behind at 8-12 s


def test_the_weights_note_names_the_shipped_network_trained_for_the_datas_scans():
    """With the general weights, the note names another shipped network where it was trained for the data's median scan
    interval and a provenance measured it ahead of the general one: real-5s at 4.5-5.5 s, real at 1 s, real-11s at
    10-12 s, real-4.5-12s at 8 s, with the numbers of those provenance files; nothing at other intervals, with other
    weights loaded, or without intervals."""
    import json

    from immnet.checkpoints import provenance_file, shipped
    from immnet.tracking.advice import load_provenance, weights_note

    general = shipped("general")
    own = load_provenance(general)
    five = json.loads(provenance_file(shipped("real-5s")).read_text())["tests"]["quickstart-5s"]["metrics"]
    note = weights_note(general, own, [4.6, 5.0, 5.2, np.nan])
    assert "--weights real-5s" in note and "4.5-5.5 s" in note and "real flights (quickstart-5s)" in note
    assert f"{five['immnet-real-5s']['avg']:.3f} m against the general one's {five['immnet-general']['avg']:.3f}" in note
    one = json.loads(provenance_file(shipped("real")).read_text())["tests"]["quickstart-1s"]["metrics"]
    note = weights_note(general, own, [1.0] * 5)  # real's own provenance, both networks in one run
    assert "--weights real " in note
    assert f"{one['immnet-real']['avg']:.3f} m against the general one's {one['immnet-general']['avg']:.3f}" in note
    eleven = json.loads(provenance_file(shipped("real-11s")).read_text())["tests"]["quickstart-11s"]["metrics"]
    note = weights_note(general, own, [10.4, 11.0, 11.9])
    assert "--weights real-11s" in note and "10-12 s" in note and "real flights (quickstart-11s)" in note
    assert f"{eleven['immnet-real-11s']['avg']:.3f} m against the general one's {eleven['immnet-general']['avg']:.3f}" in note
    note = weights_note(general, own, [8.0, 8.0])  # between the real networks' own: the one for 4.5-12 s
    assert "--weights real-4.5-12s" in note and "real flights (quickstart-7s)" in note
    assert weights_note(general, own, [3.0, 3.0]) is None and weights_note(general, own, [1.0, 2.0, 2.0]) is None
    for other, dt in (("real-5s", 5.0), ("3dlast", 1.0)):
        assert weights_note(shipped(other), load_provenance(shipped(other)), [dt]) is None
    assert weights_note(general, own, []) is None


@pytest.mark.parametrize("weights", ["general", "real-5s", None])
def test_immnet_track_names_the_5s_weights_for_5s_scans_with_the_general_weights_only(tmp_path, capsys, weights):
    """The general weights name real-5s for 5 s scans; real-5s itself and the bank (the default, which runs it) do
    not."""
    path = _one_track_csv(tmp_path / "in.csv", np.arange(12) * 5.0, seed=4, r=10.0)
    args = ["track", "--input", str(path), "--output", str(tmp_path / "o.csv")] + (["--weights", weights] if weights else [])
    assert main(args) == 0
    assert ("--weights real-5s" in capsys.readouterr().err) == (weights == "general")


def test_the_bank_note_counts_a_member_where_the_bank_runs_it():
    """``advice._takes`` reads from a provenance (or, for the 3D-LAST network, whose provenance names none, from the
    weights table) what ``NetworkBank.takes`` decides from the loaded network, for every member: a constant scan
    interval from 0.5 to 14 s, a network trained over a range taking a longer one cut into missed scans (real-5s at
    10 s, real-11s not at 13 s), the general network not where the 3D-LAST network takes the track (``DEFER``, 1 s),
    where the bank's note is not given."""
    from immnet.checkpoints import shipped
    from immnet.tracking import Tracker
    from immnet.tracking.advice import _table_scans, _takes, bank_note, load_provenance

    bank = Tracker.pretrained()
    for dt in np.arange(0.5, 14.01, 0.25):
        takes = bank.takes(torch.full((1, 4), float(dt), dtype=torch.float64))[0].tolist()
        last = _takes(_table_scans("3dlast"), float(dt))
        assert last == (dt == 1.0)
        for name, took in zip(bank.names, takes):
            prov = load_provenance(shipped(name)) or {}
            if name == "3dlast":
                assert last == took
            elif name == "general":
                assert (_takes(prov, float(dt)) and not last) == took, (name, dt)
            else:
                assert _takes(prov, float(dt)) == took, (name, dt)
    assert bank_note(np.ones(10)) is None
    assert _takes(load_provenance(shipped("real-5s")), 10.0) and not _takes(load_provenance(shipped("real-11s")), 13.0)


def test_plain_kalmannet_tracks_at_the_datas_intervals():
    """KalmanNetMethod on a network trained over a range of intervals runs its expert at each scan's interval (5 s
    here), as its check accepts them, not at the network's nominal dt; at the nominal dt as before."""
    from tensordict import TensorDict

    from immnet.checkpoints import shipped
    from immnet.tracking.methods import KalmanNetMethod

    method = KalmanNetMethod(str(shipped("general")), expert="cv")
    g = torch.Generator().manual_seed(0)
    z = torch.cumsum(torch.randn(3, 12, 3, generator=g, dtype=torch.float64) * 30 + 200, 1)
    out = {}
    for dt in (method.net.dt, 5.0):
        out[dt] = method.track(TensorDict({keys.MEASUREMENTS: z, keys.DT: torch.full((3,), dt)}, batch_size=[3]))
    with torch.no_grad():
        alone = method.net.rollout(z.float().unsqueeze(1).expand(-1, method.net.n_experts, -1, -1), experts_alone=True,
                                   intervals=torch.full((3, 12), 5.0))[0][keys.STATE][:, :, 0]
    assert torch.equal(out[5.0][keys.STATE], alone.double())
    assert not torch.equal(out[5.0][keys.STATE], out[method.net.dt][keys.STATE])
