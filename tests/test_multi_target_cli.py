"""``immnet track`` on a radar's unlabelled plots (a CSV without track_id): the multi-target tracker from the command
line, its CSV formats and refusals, the scene writer's CSV read back, the radar display (issue 63)."""

import csv
import math

import numpy as np
import pytest

from immnet.cli import main
from immnet.tracking.cli import DEFAULT_FILTER
from immnet.data.csvio import COV_COLUMNS, PLOT_OUT_COLUMNS
from tiny_runs import write_csv

T, DT, R_STD = 30, 2.0, 30.0
MISSED = (22, 1)  # (scan, target): the one plot left out
SIGMAS = ("--sigma-range", "30", "--sigma-azimuth", "0.05", "--sigma-elevation", "0.05")


def _truth() -> np.ndarray:
    """Two flights at 200 m/s, 30 degrees apart, through the same point (20 km east, 25 km north, 5 km up) at scan
    15: ``[T, 2, 3]`` ENU (m)."""
    a = np.radians(15.0)
    v = 200.0 * np.array([[np.cos(a), np.sin(a), 0.0], [np.cos(a), -np.sin(a), 0.0]])
    k = np.arange(T)[:, None, None] - 15
    return np.array([20e3, 25e3, 5e3]) + k * DT * v[None]


def _scans(noise, seed=3):
    """Per scan ``(t text, plots [n, 3])``: each target's position plus ``noise(rng, truth)``, in an order drawn per
    scan, the plot of ``MISSED`` left out."""
    rng = np.random.default_rng(seed)
    out = []
    for k, pos in enumerate(_truth()):
        plots = [noise(rng, p) for j, p in enumerate(pos) if (k, j) != MISSED]
        out.append((repr(k * DT + 100.0), [plots[i] for i in rng.permutation(len(plots))]))
    return out


def _cartesian(rng, p):
    return p + rng.normal(0.0, R_STD, 3)


def _polar(rng, p):
    """Range (m), azimuth (degrees clockwise from north) and elevation (degrees) of ``p``, with noise."""
    rho = float(np.linalg.norm(p))
    az = math.degrees(math.atan2(p[0], p[1])) % 360.0
    el = math.degrees(math.asin(p[2] / rho))
    return np.array([rho + rng.normal(0, 30.0), az + rng.normal(0, 0.05), el + rng.normal(0, 0.05)])


def _rows(scans):
    return [[t, *map(repr, map(float, p))] for t, plots in scans for p in plots]


def _read(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _are_the_trackers_tracks(rows, scene, filter_name, cover=None):
    """The CSV rows are the tracks of ``MultiTargetTracker(filter_name, cover=cover)`` stepped through the scene's own
    arrays: the same ids at the same scans (at least three tracks), positions within a metre (the CSV's covariances
    are converted from its text)."""
    from immnet.filters.multi import MultiTargetTracker

    tracker = MultiTargetTracker(filter_name, cover=cover)
    want = [(str(rep.track_id), repr(t), rep.state[[0, 3, 6]]) for t, z, cov in scene.scans()
            for rep in tracker.step(t, z, cov)]
    assert len({w[0] for w in want}) >= 3
    assert [(r["track_id"], r["t"]) for r in rows] == [w[:2] for w in want]
    got = np.array([[float(r[c]) for c in "xyz"] for r in rows])
    assert np.abs(got - np.array([w[2] for w in want])).max() < 1.0


def _track(tmp_path, header, scans, *extra):
    src = write_csv(tmp_path / "plots.csv", header, _rows(scans))
    out = tmp_path / "tracks.csv"
    assert main(["track", "--input", str(src), "--output", str(out), *extra]) == 0
    return _read(out)


def _check_crossing(rows, tol):
    """Two ids, each following one target throughout, before and after the crossing (the nearest truth, within
    ``tol`` m at every scan, the same one wherever they are apart); rows only
    from the confirming scan (the track score: the seed's scan 0, confirmed on the third plot, at scan 2) on, two a
    scan; ``updated`` 0 only for the missed target's track at its missed scan."""
    truth = _truth()
    assert [r["t"] for r in rows[:2]] == [repr(2 * DT + 100.0)] * 2 and len(rows) == 2 * (T - 2)
    follows = {}
    for r in rows:
        k = round((float(r["t"]) - 100.0) / DT)
        pos = np.array([float(r[c]) for c in "xyz"])
        d = np.linalg.norm(truth[k] - pos, axis=1)
        assert d.min() < tol, (r["track_id"], k, d)
        if abs(k - 15) > 2:  # the targets over 600 m apart: which one a track is on is plain
            follows.setdefault(r["track_id"], set()).add(int(d.argmin()))
        assert r["updated"] == ("0" if (k, int(d.argmin())) == MISSED else "1")
    assert len(follows) == 2 and all(len(s) == 1 for s in follows.values())
    assert set.union(*follows.values()) == {0, 1}
    assert sum(r["updated"] == "0" for r in rows) == 1


def test_cartesian_plots_two_crossing_targets_keep_their_ids(tmp_path):
    """t,x,y,z with --r: the output is the tracker's own, row for row (state, covariance), for its confirmed tracks."""
    from immnet.filters.multi import MultiTargetTracker

    scans = _scans(_cartesian)
    rows = _track(tmp_path, ["t", "x", "y", "z"], scans, "--r", str(R_STD), "--method", "real-imm-singer")
    assert list(rows[0]) == list(PLOT_OUT_COLUMNS)
    _check_crossing(rows, tol=150.0)
    assert all(r[c] == "" for r in rows for c in ("p_cv", "p_ca", "p_ctp", "p_ctm"))  # modes per axis: none
    tracker = MultiTargetTracker("real-imm-singer", r=R_STD)
    want = [(str(rep.track_id), t, rep) for t, plots in scans
            for rep in tracker.step(float(t), np.array([[float(repr(float(v))) for v in p] for p in plots]))]
    assert [(r["track_id"], r["t"]) for r in rows] == [(i, t) for i, t, _ in want]
    got = np.array([[float(r[c]) for c in PLOT_OUT_COLUMNS[2:11]] for r in rows])
    np.testing.assert_allclose(got, np.stack([w[2].state for w in want]), rtol=0, atol=1e-6)
    cov = np.array([[float(r[c]) for c in ("cov_xx", "cov_vyvy", "cov_zvz")] for r in rows])
    ref = np.stack([w[2].cov[[0, 4, 6], [0, 4, 7]] for w in want])
    np.testing.assert_allclose(cov, ref, rtol=1e-8)
    assert all(r[c] != "" for r in rows for c in COV_COLUMNS)


def test_polar_plots_two_crossing_targets_keep_their_ids(tmp_path):
    """t,range,azimuth,elevation with the radar's stds; JPDA too."""
    scans = _scans(_polar)
    _check_crossing(_track(tmp_path, ["t", "range", "azimuth", "elevation"], scans, *SIGMAS), tol=150.0)
    (tmp_path / "tracks.csv").unlink()
    _check_crossing(_track(tmp_path, ["t", "range", "azimuth", "elevation"], scans, *SIGMAS, "--associator", "jpda",
                           "--pd", "0.95", "--clutter-density", "1e-13"), tol=150.0)


def test_joint_imm_gives_the_data_modes(tmp_path):
    """--method real-imm (joint modes CV, CA, CT+2, CT-2 deg/s): the mode columns are each model's probability, as the
    tracker's filter holds it, summed into its data mode."""
    from immnet.filters.multi import MultiTargetTracker

    scans = _scans(_cartesian)
    rows = _track(tmp_path, ["t", "x", "y", "z"], scans, "--r", str(R_STD), "--method", "real-imm")
    tracker = MultiTargetTracker("real-imm", r=R_STD)
    want = []
    for t, plots in scans:
        tracker.step(float(t), np.array([[float(repr(float(v))) for v in p] for p in plots]))
        mu = tracker.filter.mode_probs()[tracker.confirmed, 0]  # [K, M]: CV, CA, CT+, CT-
        want += list(mu)
    got = np.array([[float(r[c]) for c in ("p_cv", "p_ca", "p_ctp", "p_ctm")] for r in rows])
    np.testing.assert_allclose(got, np.array(want), rtol=0, atol=1e-6)
    np.testing.assert_allclose(got.sum(1), 1.0, atol=4e-6)


def test_a_scan_without_plots_and_sigma_columns(tmp_path):
    """``t,,,`` is a scan without plots (the tracks coast: updated 0); per-row stds as the single-target CSV takes
    them give what the options give; scans without any plot make no track, a header alone and an empty display."""
    scans = _scans(_polar)
    header = ["t", "range", "azimuth", "elevation", "sigma_range", "sigma_azimuth", "sigma_elevation"]
    rows = []
    for k, (t, plots) in enumerate(scans):
        if k == 20:
            rows.append([t, "", "", "", "", "", ""])
            continue
        rows += [[t, *map(repr, map(float, p)), "30", "0.05", "0.05"] for p in plots]
    src = write_csv(tmp_path / "p.csv", header, rows)
    assert main(["track", "--input", str(src), "--output", str(tmp_path / "a.csv")]) == 0
    got = _read(tmp_path / "a.csv")
    gap = [r for r in got if r["t"] == scans[20][0]]
    assert len(gap) == 2 and all(r["updated"] == "0" for r in gap)
    write_csv(tmp_path / "q.csv", header[:4], [r[:4] for r in rows])
    assert main(["track", "--input", str(tmp_path / "q.csv"), "--output", str(tmp_path / "b.csv"), *SIGMAS]) == 0
    assert got == _read(tmp_path / "b.csv")
    write_csv(tmp_path / "none.csv", header[:4], [[t, "", "", ""] for t, _ in scans])  # scans, none with a plot
    assert main(["track", "--input", str(tmp_path / "none.csv"), "--output", str(tmp_path / "c.csv"), *SIGMAS,
                 "--figure", str(tmp_path / "c.png")]) == 0
    assert (tmp_path / "c.csv").read_text().splitlines() == [",".join(PLOT_OUT_COLUMNS)]
    assert (tmp_path / "c.png").stat().st_size > 5_000


GOOD = [["0", "1000", "2000", "3000"], ["2", "1400", "2000", "3000"]]
GOOD_POLAR = [["0", "10000", "20", "3"], ["2", "10400", "20", "3"]]
CART = ["t", "x", "y", "z"]
POLAR = ["t", "range", "azimuth", "elevation"]
R_COLS = "r_xx,r_xy,r_xz,r_yy,r_yz,r_zz"
SIGMA_HINT = ("--sigma-range METRES --sigma-azimuth DEG --sigma-elevation DEG, or the columns sigma_range,"
              "sigma_azimuth,sigma_elevation")
REFUSALS = [
    (["t", "x", "y", "z", "range"], GOOD, ("--r", "30"),
     "line 1: columns x,y,z,range mix Cartesian (x,y,z) and polar (range,azimuth,elevation) positions: give one of "
     "the two"),
    (CART, [*GOOD, ["5", "1", "2", "3"], ["4", "1", "2", "3"]], ("--r", "30"),
     "line 5: time 4 is before the previous scan's time 5 (line 4): scans come in time order, the plots of a scan "
     "together under its t"),
    (CART, [*GOOD, ["a", "3", "1", "2", "3"]], ("--r", "30"),
     "line 4: 5 fields, but the header has 4 (t,x,y,z)"),
    (["track_id", *CART], [["a", *GOOD[0]], ["", *GOOD[1]]], ("--method", "imm-tuned"),
     "line 3: column 'track_id' is empty: in a CSV with a track_id column every row names its track (unlabelled "
     "plots, for the multi-target tracker, have no such column)"),
    (CART, [*GOOD, ["3", "1", "", "3"]], ("--r", "30"),
     "line 4: column 'y' is empty in a plot: a plot gives x,y,z, all three (a scan without plots leaves all three "
     "empty)"),
    (POLAR, [["0", "", "2", ""]], SIGMAS,
     "line 2: columns 'range', 'elevation' are empty in a plot: a plot gives range,azimuth,elevation, all three (a "
     "scan without plots leaves all three empty)"),
    (CART, [GOOD[0], ["0", "", "", ""]], ("--r", "30"),
     "line 3: the scan at time 0 has a plot (line 2) and an empty row (line 3: a scan without plots): give one or "
     "the other"),
    (CART, [["1e20", "1", "2", "3"], ["100000000000000000001", "1", "2", "3"]], ("--r", "30"),
     "line 3: time 100000000000000000001 and the previous scan's time 1e20 are one number in float64: give the plots "
     "of one scan one t"),
    (CART, [["", "1", "2", "3"]], ("--r", "30"), "line 2: column 't' is empty"),
    (POLAR, [["0", "-5", "2", "3"]], SIGMAS, "line 2: column 'range' is -5: a slant range is > 0 (m)"),
    (POLAR, GOOD_POLAR, (), f"line 1: range,azimuth,elevation rows need the radar's stds: give {SIGMA_HINT}"),
    (CART, GOOD, (), f"x,y,z plots without the columns {R_COLS} need their measurement std, which {DEFAULT_FILTER} "
                     f"does not assume: give --r METRES"),
    (POLAR, GOOD_POLAR, (*SIGMAS, "--r", "30"),
     "--r and the CSV's plots both give the plots' measurement noise: give one of the two"),
    (CART, GOOD, ("--r", "30", "--weights", "3dlast"),
     "--weights does not apply to plots without a track_id column (the multi-target tracker): its per-track filter "
     "is named by --method NAME (a model-based method, or a shipped network such as radar-5s)"),
    (CART, GOOD, ("--r", "30", "--checkpoint", "my.ckpt"),
     "--checkpoint does not apply to plots without a track_id column (the multi-target tracker): its per-track "
     "filter is named by --method NAME (a model-based method, or a shipped network such as radar-5s), not a "
     "checkpoint file"),
    (CART, GOOD, ("--r", "30", "--method", "radar-5s", "--associator", "jpda"),
     "radar-5s is a network: JPDA needs a mixture update over a track's gated plots, and a network's carry (its "
     "recurrent memory and noise estimate) is one track's history, which no weighted blend stands for; use GNN "
     "(associator gnn)"),
    (CART, GOOD, ("--r", "30", "--method", "bank"),
     "bank is several networks weighed per track, not one: the multi-target tracker's network filters are the "
     "shipped networks by name (general, real, real-5s, real-11s, real-4.5-12s, 3dlast, ...)"),
    (CART, GOOD, ("--r", "30", "--max-coast", "60"),
     "--max-coast does not apply to plots without a track_id column (the multi-target tracker): a confirmed track "
     "is deleted after missed scans in a row (once they span its min_coast seconds), not after a time alone"),
    (CART, GOOD, ("--r", "30", "--guard", "none"),
     "--guard does not apply to plots without a track_id column (the multi-target tracker): it has no range guard"),
    (CART, GOOD, ("--r", "30", "--adapt"),
     "--adapt does not apply to plots without a track_id column (the multi-target tracker): its filters keep the "
     "method's own process noise"),
    (CART, GOOD, ("--r", "30", "--pd", "0.8"), "--pd is JPDA's (--associator jpda): GNN does not use it"),
    (CART, GOOD, ("--r", "30", "--associator", "jpda", "--pd", "1.5"),
     "--pd is the probability that an aircraft is detected, in (0, 1]; got 1.5"),
    (CART, GOOD, ("--r", "30", "--associator", "jpda", "--clutter-density", "0"),
     "--clutter-density is the false plots per m^3, a finite number > 0; got 0"),
    (CART, GOOD, ("--r", "30", "--min-elevation", "2"),
     "--min-elevation is the radar's cover with --max-range: give --max-range METRES too"),
    (CART, GOOD, ("--r", "30", "--max-range", "-5"),
     "--max-range is the slant range the radar sees up to, a finite number of metres > 0; got -5"),
    (CART, GOOD, ("--r", "30", "--max-range", "9e4", "--min-elevation", "90"),
     "--min-elevation is in degrees, in [-90, 90); got 90"),
    (CART, GOOD, ("--r", "30", "--scene", "s.npz"),
     "--scene marks the clutter on --figure's radar display: give --figure FILE.png too"),
    (CART, GOOD, ("--r", "30", "--figure", "radar.jpg"),
     "--figure radar.jpg: the radar display is a PNG file (a name ending .png)"),
    (CART, GOOD, ("--r", "30", "--method", "clairvoyant"),
     "clairvoyant is a ClairvoyantKF: the multi-target tracker's filters are the model-based IMMs and Kalman filters "
     "(IMMTracker, PerAxisIMMTracker, KalmanFilterTracker) and the shipped networks by their weights' name "
     "(radar-5s, real-5s, ...)"),
    (["track_id", *CART], [["a", *GOOD[0]]], ("--method", "imm-tuned", "--associator", "jpda"),
     "--associator is the multi-target tracker's, for a CSV of plots without a track_id column; IN has a track_id "
     "column"),
]


@pytest.mark.parametrize("header, rows, extra, message", REFUSALS, ids=[m[:40] for *_, m in REFUSALS])
def test_refusals_are_one_line_and_leave_nothing(tmp_path, capsys, monkeypatch, header, rows, extra, message):
    monkeypatch.chdir(tmp_path)
    src = write_csv(tmp_path / "plots.csv", header, rows)
    assert main(["track", "--input", str(src), "--output", "tracks.csv", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == "immnet track: error: " + message.replace("IN", str(src))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plots.csv"]


def _scene(tmp_path, index=0):
    from immnet.data import scenes as S

    spec = S.SceneSpec(duration=120.0, targets=3, crossing_pairs=1, close_pairs=0, clutter=3.0, pd=0.9)
    scene = S.last_scene(index, spec, seed=0)
    return scene, S.save_scene(scene, tmp_path / f"s{index}.npz"), S.write_plots_csv(scene, tmp_path / f"s{index}.csv")


def test_the_scene_writers_csv_is_what_track_reads(tmp_path, capsys):
    """``immnet data scenes``' CSV (``write_plots_csv``) tracked as it is, with its scene's stds: its scans are the
    scene's (``--scene`` checks them plot by plot, for the clutter on the figure), and its tracks are those of the
    tracker stepped through the scene's own arrays (ENU plots with their first-order covariance, where the CSV's are
    converted unbiased from its text: the same tracks, within a metre); the radar display is written. Another scene's
    file is refused as not this CSV's, leaving nothing."""
    scene, npz, plots = _scene(tmp_path)
    spec = scene.meta["spec"]
    stds = ("--sigma-range", repr(spec["sigma_range"]), "--sigma-azimuth", repr(spec["sigma_azimuth_deg"]),
            "--sigma-elevation", repr(spec["sigma_elevation_deg"]))
    out, png = tmp_path / "tracks.csv", tmp_path / "radar.png"
    assert main(["track", "--input", str(plots), "--output", str(out), *stds, "--figure", str(png),
                 "--scene", str(npz)]) == 0
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith(
        f"tracked {len(scene)} scans, {len(scene.plots)} plots with {DEFAULT_FILTER}: mtt-imm-5s (GNN)")
    rows = _read(out)
    _are_the_trackers_tracks(rows, scene, DEFAULT_FILTER)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    from immnet.filters.multi import Cover

    out.unlink()  # told a cover that ends inside the scene: tracks beyond it end at their first miss there
    edge = float(np.median(np.linalg.norm(scene.plots, axis=1)))
    assert main(["track", "--input", str(plots), "--output", str(out), *stds, "--max-range", repr(edge),
                 "--min-elevation", "1"]) == 0
    capsys.readouterr()
    covered = _read(out)
    assert len(covered) < len(rows)
    _are_the_trackers_tracks(covered, scene, DEFAULT_FILTER, Cover(edge, 1.0))
    _, other, _ = _scene(tmp_path, 1)
    out.unlink()
    png.unlink()
    assert main(["track", "--input", str(plots), "--output", str(out), *stds, "--figure", str(png),
                 "--scene", str(other)]) == 2
    assert capsys.readouterr().err.strip().startswith(f"immnet track: error: --scene {other}: not the scene of this CSV")
    assert not out.exists() and not png.exists()


def test_the_default_filter_takes_the_csvs_median_scan_interval(tmp_path, capsys):
    """The default per-track filter (``real-imm-by-interval``) is chosen by the median interval between the CSV's
    scans, not by its first: a CSV of 4.5-5.5 s scans whose second scan was left out (its first interval about 10 s)
    is still tracked by ``mtt-imm-5s``, to the row as by that filter by name."""
    scene, _, plots = _scene(tmp_path)
    lines = plots.read_text().splitlines()
    second = sorted({line.split(",")[0] for line in lines[1:]}, key=float)[1]
    cut = tmp_path / "cut.csv"
    cut.write_text("\n".join(line for line in lines if line.split(",")[0] != second) + "\n")
    spec = scene.meta["spec"]
    stds = ("--sigma-range", repr(spec["sigma_range"]), "--sigma-azimuth", repr(spec["sigma_azimuth_deg"]),
            "--sigma-elevation", repr(spec["sigma_elevation_deg"]))
    out, named = tmp_path / "default.csv", tmp_path / "named.csv"
    assert main(["track", "--input", str(cut), "--output", str(out), *stds]) == 0
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith(
        f"tracked {len(scene) - 1} scans, {len(scene.plots) - len(scene.scan(1)[1])} plots with {DEFAULT_FILTER}: "
        f"mtt-imm-5s (GNN)")
    assert main(["track", "--input", str(cut), "--output", str(named), *stds, "--method", "mtt-imm-5s"]) == 0
    assert out.read_text() == named.read_text()


def test_a_shipped_network_as_the_per_track_filter(tmp_path, capsys):
    """``--method radar-5s``: the scene's CSV tracked with the network as each track's filter gives the tracks of
    ``MultiTargetTracker("radar-5s")`` stepped through the scene's own arrays (within a metre: the CSV's covariances
    are converted from its text), with the data modes' probabilities the network reports (each row sums to 1)."""
    scene, _, plots = _scene(tmp_path)
    spec = scene.meta["spec"]
    stds = ("--sigma-range", repr(spec["sigma_range"]), "--sigma-azimuth", repr(spec["sigma_azimuth_deg"]),
            "--sigma-elevation", repr(spec["sigma_elevation_deg"]))
    out = tmp_path / "tracks.csv"
    assert main(["track", "--input", str(plots), "--output", str(out), *stds, "--method", "radar-5s"]) == 0
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith(
        f"tracked {len(scene)} scans, {len(scene.plots)} plots with radar-5s (GNN)")
    rows = _read(out)
    _are_the_trackers_tracks(rows, scene, "radar-5s")
    probs = np.array([[float(r[c]) for c in ("p_cv", "p_ca", "p_ctp", "p_ctm")] for r in rows])
    np.testing.assert_allclose(probs.sum(1), 1.0, atol=1e-5)


def test_long_inputs_say_where_they_are_and_the_help_names_the_default_filter(tmp_path, capsys, monkeypatch):
    """From ``LONG`` scans a run prints progress lines on stderr (here, not a terminal: plain lines); the help's
    defaults (the filter, JPDA's pd and clutter density) are the tracker's."""
    import inspect

    from immnet.filters import multi
    from immnet.tracking import cli, multi_cli

    assert cli.DEFAULT_FILTER == multi.DEFAULT_FILTER
    defaults = inspect.signature(multi.MultiTargetTracker).parameters
    assert (defaults["pd"].default, defaults["clutter_density"].default) == (0.9, 1e-12)  # as the help says
    monkeypatch.setattr(multi_cli, "LONG", T)
    _track(tmp_path, ["t", "x", "y", "z"], _scans(_cartesian), "--r", str(R_STD))
    err = capsys.readouterr().err.splitlines()
    assert err[0] == f"[track] 0/{T} scans" and err[-2].startswith(f"[track] {T} scans in ")
    monkeypatch.setattr(multi_cli, "LONG", T + 1)
    (tmp_path / "tracks.csv").unlink()
    _track(tmp_path, ["t", "x", "y", "z"], _scans(_cartesian), "--r", str(R_STD))
    assert not any(line.startswith("[track]") for line in capsys.readouterr().err.splitlines())
