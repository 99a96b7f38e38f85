"""``immnet track`` and the ``Tracker`` at the edge: CSV times and paths, gated measurements, no
estimate before a track's first detection, times as given, segments at coasting gaps (issue 20)."""

import csv
import math
import os
import tracemalloc

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from immnet import keys
from immnet.cli import main
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.tracking import Tracker

TOL = 0.1
"""Tracking the same scans in another batch composition (float32, other BLAS sums) moves an estimate by up
to a few cm (cm/s); a wrong segment or a coasted gap moves it by metres."""
COLUMNS = ("x", "vx", "ax", "y", "vy", "ay", "z", "vz", "az", "p_cv", "p_ca", "p_ctp", "p_ctm")


@pytest.fixture(scope="module")
def tracker():
    """The fixed-grid path (a network trained at one interval: the 3D-LAST weights); the general network takes each
    row at its own time (tests/test_tracking_intervals.py)."""
    return Tracker.pretrained("3dlast", guard=None)


@pytest.fixture(scope="module")
def scans():
    return generate(3, seed=8, spec=DataSpec(T=60, min_segment=15))["measurements"].double().numpy()


def _write(path, rows, bom=False):
    with open(path, "w", newline="", encoding="utf-8-sig" if bom else "utf-8") as f:
        w = csv.writer(f)
        w.writerow(["track_id", "t", "x", "y", "z"])
        w.writerows(rows)


def _num(v):
    return repr(float(v))


def _rows(z, tid="a", t0=0.0, dt=1.0):
    return [[tid, _num(t0 + k * dt), *(("", "", "") if np.isnan(zk).any() else map(_num, zk))] for k, zk in enumerate(z)]


def _track(tmp_path, rows, *extra, name="in.csv", bom=False):
    _write(tmp_path / name, rows, bom)
    out = tmp_path / ("out-" + name)
    code = main(["track", "--input", str(tmp_path / name), "--output", str(out), "--weights", "3dlast", "--guard", "none",
                 *extra])
    assert code == 0
    with open(out, newline="") as f:
        return list(csv.DictReader(f))


def _values(row):
    return np.array([math.nan if row[c] == "" else float(row[c]) for c in COLUMNS])


# --- item 2: inputs at the edge ---------------------------------------------------------------

def test_a_byte_order_mark_is_accepted(tmp_path, scans):
    """Issue 20, item 2: a UTF-8 BOM (as spreadsheet programs write) is not part of the first column's
    name; the output is the one of the same file without it."""
    rows = _rows(scans[0, :10])
    with_bom = _track(tmp_path, rows, name="bom.csv", bom=True)
    assert (tmp_path / "bom.csv").read_bytes().startswith(b"\xef\xbb\xbf")
    assert with_bom == _track(tmp_path, rows, name="plain.csv")


@pytest.mark.parametrize("text", ["inf", "-inf", "nan", "Infinity"])
def test_a_non_finite_time_is_refused_by_line(tmp_path, text, capsys):
    """Issue 20, item 2: CSV times are finite; a non-finite one is named by its line, nothing is written."""
    _write(tmp_path / "in.csv", [["a", 0, 1, 2, 3], ["a", text, 1, 2, 3]])
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(tmp_path / "o.csv")]) == 2
    assert f"line 3: column 't' is not a finite time: {text!r}" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path)) == ["in.csv"]


@pytest.mark.parametrize("how", ["same", "dotdot", "symlink", "hardlink"])
def test_output_that_is_the_input_is_refused_and_the_input_kept(tmp_path, scans, how, capsys):
    """Issue 20, item 2: ``--output`` naming the input file (also by ``..``, a symlink or a hard link)
    is refused before anything is written; the input's bytes are unchanged."""
    (tmp_path / "sub").mkdir()
    _write(tmp_path / "in.csv", _rows(scans[0, :5]))
    before = (tmp_path / "in.csv").read_bytes()
    out = {"same": tmp_path / "in.csv", "dotdot": tmp_path / "sub" / ".." / "in.csv",
           "symlink": tmp_path / "link.csv", "hardlink": tmp_path / "hard.csv"}[how]
    if how == "symlink":
        out.symlink_to(tmp_path / "in.csv")
    if how == "hardlink":
        os.link(tmp_path / "in.csv", out)
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(out), "--guard", "none"]) == 2
    assert "is the input file" in capsys.readouterr().err
    assert (tmp_path / "in.csv").read_bytes() == before
    assert not [p for p in os.listdir(tmp_path) if "partial" in p]


@pytest.mark.parametrize("value,extra", [("inf", ()), ("-inf", ()), ("1e30", ()), ("5e5", ("--max-position", "1e5"))],
                         ids=["inf", "-inf", "1e30", "beyond-max-position"])
def test_a_measurement_no_sensor_reports_is_a_counted_missed_detection(tmp_path, scans, value, extra, capsys):
    """Issue 20, item 2: one measurement of inf / 1e30 (or beyond ``--max-position``) is a missed
    detection: counted on stderr, the rest of the track finite and equal to the same CSV with that
    row's x, y, z empty."""
    rows = _rows(scans[0, :25])
    bad = [list(r) for r in rows]
    bad[12][2] = value
    missed = [list(r) for r in rows]
    missed[12][2:] = ["", "", ""]
    got = _track(tmp_path, bad, *extra, name="bad.csv")
    assert "gated 1 measurement(s)" in capsys.readouterr().err
    want = _track(tmp_path, missed, *extra, name="missed.csv")
    assert got == want
    assert np.isfinite(np.stack([_values(r) for r in got])).all()


def test_the_tracker_gates_and_counts(tracker, scans):
    """Issue 20, item 2: ``Tracker.track`` and ``Tracker.step`` treat inf / 1e30 as missed detections and
    count them in ``n_gated``; the estimates equal those with NaN there."""
    z = torch.from_numpy(scans[:, :20]).float()
    bad, nan = z.clone(), z.clone()
    bad[0, 5, 1], bad[2, 9, 0] = math.inf, 1e30
    nan[0, 5], nan[2, 9] = math.nan, math.nan
    got, want = tracker.track(bad), tracker.track(nan)
    assert tracker.n_gated == 0  # the last call's count
    tracker.track(bad)
    assert tracker.n_gated == 2
    assert torch.isfinite(got["state"]).all()
    torch.testing.assert_close(got["state"], want["state"], rtol=0, atol=0)
    tracker.reset(3)
    for t in range(20):
        out = tracker.step(bad[:, t])
        torch.testing.assert_close(out[keys.FUSED], want["state"][:, t], rtol=1e-5, atol=TOL)
    assert tracker.n_gated == 2


# --- item 3: no made-up output ----------------------------------------------------------------

def test_immnet_has_no_estimate_before_the_first_detection(tracker, scans):
    """Issue 20, item 3: before a track's first detection every output is NaN (a track without any
    detection: all NaN), in ``track`` and ``step``; from the first detection on the estimates are
    those of the track started there (its leading scans cut off)."""
    z = torch.from_numpy(scans[:, :20]).float()
    z[0, :4] = math.nan
    z[1] = math.nan
    out = tracker.track(z)
    for key in ("state", "mode_probs", "expert_probs", "expert_post"):
        assert torch.isnan(out[key][0, :4]).all() and torch.isnan(out[key][1]).all(), key
        assert torch.isfinite(out[key][0, 4:]).all() and torch.isfinite(out[key][2]).all(), key
    alone = tracker.track(z[0:1, 4:])
    torch.testing.assert_close(out["state"][0, 4:], alone["state"][0], rtol=1e-5, atol=TOL)
    tracker.reset(3)
    for t in range(20):
        step = tracker.step(z[:, t])
        for key in (keys.FUSED, keys.MODE_PROBS, keys.EXPERT_POST, keys.EXPERT_PROBS):
            assert torch.isnan(step[key][1]).all() and (torch.isnan(step[key][0]).all() == (t < 4)), (key, t)


def test_csv_fields_are_empty_before_the_first_detection(tmp_path, scans):
    """Issue 20, item 3: in the CSV, rows of a track before its first detection (and every row of a track
    without one) have empty estimate and mode-probability fields."""
    z = scans[0, :10].copy()
    z[:3] = np.nan
    rows = _rows(z, "a") + _rows(np.full((4, 3), np.nan), "never")
    out = _track(tmp_path, rows)
    for row in out:
        empty = row["track_id"] == "never" or float(row["t"]) < 3
        assert all((row[c] == "") == empty for c in COLUMNS), row


def _methods():
    from immnet.filters.methods import available_methods

    return available_methods()


@pytest.mark.parametrize("name", _methods())
def test_no_method_makes_up_an_estimate_before_the_first_detection(name):
    """Issue 20, item 3: every method of ``immnet evaluate`` (each config of configs/methods/ and the raw
    measurements) outputs NaN before a track's first detection, all NaN for a track without one, and
    finite numbers everywhere else (nothing it carries turned NaN)."""
    from immnet.filters.methods import build_method
    from tiny_runs import at_an_interval_it_takes

    data = generate(3, seed=5, spec=DataSpec(T=30, min_segment=10))
    z = data[keys.MEASUREMENTS].clone()
    z[0, :5] = math.nan
    z[1] = math.nan
    data = TensorDict({**data.to_dict(), keys.MEASUREMENTS: z}, batch_size=data.batch_size)
    method = build_method(name)
    out = method.track(at_an_interval_it_takes(method, data))
    for key in (keys.STATE, keys.MODE_PROBS):
        if key not in out.keys():
            continue
        v = out[key]
        assert torch.isnan(v[0, :5]).all() and torch.isnan(v[1]).all(), key
        assert torch.isfinite(v[0, 5:]).all() and torch.isfinite(v[2]).all(), key


# --- item 4: times as given; memory by rows ---------------------------------------------------

def test_epoch_second_times_round_trip_as_text(tmp_path, scans):
    """Issue 20, item 4: output times are the input's own text: epoch seconds keep every digit (to the
    millisecond and beyond), written as they were given."""
    times = [f"{1_733_070_000 + k}.123" for k in range(8)] + ["1733070008.1230", "1733070009.123000000"]
    rows = [["a", t, *map(_num, zk)] for t, zk in zip(times, scans[0])]
    out = _track(tmp_path, rows)
    assert [r["t"] for r in out] == times
    assert np.isfinite(np.stack([_values(r) for r in out])).all()


def test_a_huge_gap_costs_memory_by_rows_and_both_segments_are_tracked(tmp_path, scans, tracker):
    """Issue 20, item 4: 1e9 s gaps inside two tracks allocate by rows (not 2e9 scans: 48 GB of z) and
    both sides of each gap are tracked, each as the track started at its first row."""
    t0 = 1_733_070_000.0
    parts = [(tid, t, scans[i, 30 * j : 30 * j + 30]) for i, tid in enumerate("ab")
             for j, t in enumerate((t0, t0 + 29 + 1e9))]
    rows = [row for tid, t, z in parts for row in _rows(z, tid, t)]
    _write(tmp_path / "in.csv", rows)
    args = ["track", "--input", str(tmp_path / "in.csv"), "--weights", "3dlast", "--guard", "none", "--output"]
    main(args + [str(tmp_path / "warm.csv")])  # imports and caches outside the measurement
    tracemalloc.start()
    try:
        code = main(args + [str(tmp_path / "out.csv")])
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert code == 0
    assert peak < 20e6, f"peak {peak / 1e6:.1f} MB traced for 120 rows"
    with open(tmp_path / "out.csv", newline="") as f:
        got = np.stack([_values(r)[:9] for r in csv.DictReader(f)])
    for k, (_, _, z) in enumerate(parts):
        alone = tracker.track(torch.from_numpy(z[None]).float())["state"][0].double().numpy()
        np.testing.assert_allclose(got[30 * k : 30 * k + 30], alone, rtol=1e-5, atol=TOL)


def test_a_track_is_split_at_coasting_gaps(tmp_path, scans, tracker):
    """Issue 20, item 4: a gap longer than ``--max-coast`` drops the track, which restarts at its next
    detection; a shorter gap is coasted. Each segment's estimates equal tracking it alone (a separate
    ``Tracker.track`` over the segment's scans), and a missed detection after the limit has none."""
    z = scans[2, :40]
    t = np.concatenate([np.arange(10), 10 + 20 + np.arange(10), 40 + 50 + np.arange(20)])  # gaps 21 s, 51 s
    rows = [["a", _num(tk), *map(_num, zk)] for tk, zk in zip(t, z)]
    rows.insert(20, ["a", "85.0", "", "", ""])  # 36 s after the last detection: beyond 30 s, no estimate
    out = _track(tmp_path, rows)
    got = np.stack([_values(r)[:9] for r in out])
    assert np.isnan(got[20]).all()
    got = np.delete(got, 20, 0)
    seg1 = np.full((40, 3), np.nan)  # rows 0..19 on the scans 0..9 and 30..39 (20 missed scans between)
    seg1[t[:20]] = z[:20]
    for idx, seg, steps in ((slice(0, 20), seg1, t[:20]), (slice(20, 40), z[20:], np.arange(20))):
        alone = tracker.track(torch.from_numpy(seg[None]).float())["state"][0].double().numpy()
        # the scans right after the 20 coasted ones start from a covariance grown over 20 s, which carries the batch's
        # float32 rounding up to about 0.1 m/s (a wrong segment or an uncoasted gap moves the estimate by metres)
        np.testing.assert_allclose(got[idx], alone[steps], rtol=1e-5, atol=2.5 * TOL)
    # a limit below the 21 s gap splits there too
    rows.pop(20)
    short = np.stack([_values(r)[:9] for r in _track(tmp_path, rows, "--max-coast", "15", name="short.csv")])
    alone = tracker.track(torch.from_numpy(z[None, 10:20]).float())["state"][0].double().numpy()
    np.testing.assert_allclose(short[10:20], alone, rtol=1e-5, atol=TOL)


def _one_error_line(err: str) -> str:
    assert "Traceback" not in err, err[-2000:]
    lines = [s for s in err.splitlines() if s.startswith("immnet track: error: ")]
    assert len(lines) == 1, err[-2000:]
    return lines[0]


@pytest.mark.parametrize("extra,why", [
    (("--checkpoint", "CKPT"), "give --method (a method of immnet evaluate) or --checkpoint (a file of your own), not both"),
    (("--weights", "real"), "give --method (a method of immnet evaluate) or --weights (shipped weights by name), not both"),
], ids=["checkpoint", "weights"])
def test_a_method_with_a_network_is_refused_not_ignored(tmp_path, scans, extra, why, capsys):
    """Issue 60, item 8: ``--method imm-ekf`` with ``--checkpoint`` (or ``--weights``) tracked with the method and
    ignored the network without a word (exit 0); now refused in one line, nothing written."""
    from immnet.checkpoints import shipped

    _write(tmp_path / "in.csv", _rows(scans[0, :10]))
    extra = [shipped("3dlast").as_posix() if e == "CKPT" else e for e in extra]
    out = tmp_path / "o.csv"
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(out), "--method", "imm-ekf", *extra]) == 2
    assert _one_error_line(capsys.readouterr().err) == f"immnet track: error: {why}"
    assert not out.exists()


def test_a_method_with_an_npz_input_is_refused_not_ignored(tmp_path, scans, capsys):
    """``--method`` is for CSV rows: with an .npz input it was ignored (the network tracked it, exit 0)."""
    np.savez(tmp_path / "in.npz", measurements=scans[:, :10].astype(np.float32), dt=1.0)
    out = tmp_path / "o.npz"
    assert main(["track", "--input", str(tmp_path / "in.npz"), "--output", str(out), "--method", "imm-ekf"]) == 2
    assert _one_error_line(capsys.readouterr().err) == (
        f"immnet track: error: --method tracks a CSV input (each row a scan at its own time); {tmp_path / 'in.npz'} "
        f"is not one: leave --method out to track it with the network")
    assert not out.exists()


@pytest.mark.parametrize("how", [(), ("--weights", "general"), ("--weights", "3dlast"), ("--method", "imm-ekf")],
                         ids=["bank", "range-network", "one-interval-network", "method"])
def test_gated_measurements_are_reported_with_their_csv_lines(tmp_path, scans, how, capsys):
    """Issue 60, item 9: docs/tracking.md says ``immnet track`` reports the gated measurements with their CSV lines;
    only the 3D-LAST network's path did, the default (the bank), a range network and ``--method`` gave the count
    alone. Two tracks, rows interleaved, seven gated rows (inf, 1e30, a partly empty row): the count and the first
    five lines, in the file's order, for each."""
    rows = []
    for k in range(20):
        rows += [_rows(scans[0, :20])[k], _rows(scans[1, :20], tid="b")[k]]
    bad = {3: "inf", 8: "1e30", 11: "-inf", 16: "", 20: "inf", 27: "1e30", 33: "inf"}  # 0-based data rows
    for i, value in bad.items():
        rows[i][2] = value
    _write(tmp_path / "in.csv", rows)
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(tmp_path / "o.csv"), "--guard", "none",
                 *how]) == 0
    err = capsys.readouterr().err
    lines = [i + 2 for i in sorted(bad)]  # line 1 is the header
    assert (f"gated 7 measurement(s) a sensor cannot report (non-finite, or |x|, |y| or |z| > 1e+07 m) on line(s) "
            f"{', '.join(map(str, lines[:5]))}, ...: tracked as missed detections") in err, err


@pytest.mark.parametrize("where", ["x", "track_id"])
def test_a_field_over_the_csv_limit_is_refused_by_line(tmp_path, where, capsys):
    """Issue 60, item 7: a field longer than the csv module's limit (131072 characters) ended ``immnet track`` in
    ``_csv.Error: field larger than field limit``; now one line naming the file's line, nothing written."""
    import csv as csv_module

    limit = csv_module.field_size_limit()
    huge = "1" * (limit + 1) if where == "x" else "a" * (limit + 1)
    row = ["a", "1", huge, "2", "3"] if where == "x" else [huge, "1", "1", "2", "3"]
    _write(tmp_path / "in.csv", [["a", "0", "1", "2", "3"], row, ["a", "2", "1", "2", "3"]])
    out = tmp_path / "o.csv"
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(out), "--method", "imm-ekf"]) == 2
    assert _one_error_line(capsys.readouterr().err) == (
        f"immnet track: error: line 3: not readable as CSV (field larger than field limit ({limit}))")
    assert sorted(os.listdir(tmp_path)) == ["in.csv"]


@pytest.mark.parametrize("extra,why", [
    (("--robust", "-1"), "--robust is Huber's k, a finite number of standard deviations > 0; got -1"),
    (("--robust", "nan"), "--robust is Huber's k, a finite number of standard deviations > 0; got nan"),
    (("--robust", "3", "--method", "imm-ekf"),
     "--robust sets the networks' update; a --method has its own (robust: in its YAML)"),
], ids=["negative", "nan", "method"])
def test_robust_option_refusals(tmp_path, scans, extra, why, capsys):
    _write(tmp_path / "in.csv", _rows(scans[0, :10]))
    out = tmp_path / "o.csv"
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(out), *extra]) == 2
    assert _one_error_line(capsys.readouterr().err) == f"immnet track: error: {why}"
    assert not out.exists()


@pytest.mark.parametrize("weights", [(), ("--weights", "general")], ids=["bank", "general"])
def test_robust_option_tracks_as_the_api_and_holds_an_outlier(tmp_path, scans, weights):
    """``immnet track --robust 3.5`` (the bank, or shipped weights) gives ``Tracker.pretrained(name, robust=3.5)``'s
    track to the CSV's digits, and a plot 2 km off pulls it far less than without (Huber's update: k standard
    deviations at most; the test can fail)."""
    z = scans[0, :40].copy()
    z[25] += 2000.0
    rows = _rows(z)
    _write(tmp_path / "in.csv", rows)
    outs = {}
    for k in ((), ("--robust", "3.5")):
        out = tmp_path / f"o{len(k)}.csv"
        assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(out), *weights, *k]) == 0
        with open(out, newline="") as f:
            outs[len(k)] = np.stack([_values(r)[:9] for r in csv.DictReader(f)])
    truth = scans[0, :40]
    pull = {n: np.linalg.norm(o[25, [0, 3, 6]] - truth[25]) for n, o in outs.items()}
    assert pull[2] < 0.5 * pull[0], pull
    name = weights[1] if weights else "bank"
    api = Tracker.pretrained(name, robust=3.5, guard=None if weights else "checkpoint")
    want = api.track(torch.from_numpy(z[None]).double() if name == "bank" else torch.from_numpy(z[None]).float())
    np.testing.assert_allclose(outs[2][:, [0, 3, 6]], want["state"][0, :, [0, 3, 6]].double().numpy(), rtol=1e-5, atol=TOL)


def test_robust_option_is_refused_for_plots_without_track_id_and_for_rows_with_covariances(tmp_path, scans, capsys):
    """``--robust`` sets a network's update: a radar's unlabelled plots go to the multi-target tracker, whose filter is
    a ``--method``, and rows with covariances to the radar networks, which carry Huber's update already; each is
    refused in one line, nothing written."""
    plots = tmp_path / "plots.csv"
    with open(plots, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "x", "y", "z"])
        for k, zk in enumerate(scans[0, :10]):
            w.writerow([_num(5.0 * k), *map(_num, zk)])
    out = tmp_path / "o.csv"
    assert main(["track", "--input", str(plots), "--output", str(out), "--robust", "3"]) == 2
    assert _one_error_line(capsys.readouterr().err) == (
        "immnet track: error: --robust is for tracks with a track_id; the multi-target tracker's filter is a --method "
        "(e.g. radar-imm-robust-5s)")
    told = tmp_path / "told.csv"
    with open(told, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["track_id", "t", "x", "y", "z", "r_xx", "r_xy", "r_xz", "r_yy", "r_yz", "r_zz"])
        for k, zk in enumerate(scans[0, :10]):
            w.writerow(["a", _num(5.0 * k), *map(_num, zk), "900", "0", "0", "900", "0", "2500"])
    assert main(["track", "--input", str(told), "--output", str(out), "--robust", "3"]) == 2
    assert _one_error_line(capsys.readouterr().err) == (
        "immnet track: error: --robust: the default for rows with covariances carries Huber's update already (k 2.5, "
        "the radar networks'); give --weights or --checkpoint to set a network's")
    assert not out.exists()
