"""The default tracker of CSV rows that carry each detection's covariance (issue 62): a radar's plots, or ``r_xx..``
columns, are tracked by the shipped radar network of their scan band, told each plot's covariance (else by the
model-based filter told it), and Cartesian rows without a covariance by the bank as before."""

import csv

import numpy as np
import pytest

from immnet.cli import main
from immnet.tracking.advice import RADAR_BANDS, radar_default

SIGMAS = ("--sigma-range", "40", "--sigma-azimuth", "0.12", "--sigma-elevation", "0.2")


def _flight(n: int, dt: float, seed: int, jitter: float = 0.0):
    """A target 30-40 km from the radar flying a slow turn at 200 m/s, its plots (range m, azimuth deg, elevation deg)
    with the radar's noise, every ``dt`` s (U[-jitter, jitter] added), one plot in ten missed."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(np.r_[0.0, dt + rng.uniform(-jitter, jitter, n - 1)])
    heading = np.radians(30.0 + 0.5 * t)  # 0.5 deg/s
    speed = 200.0
    e = 20_000.0 + np.cumsum(np.r_[0.0, speed * np.sin(heading[:-1]) * np.diff(t)])
    nn = 25_000.0 + np.cumsum(np.r_[0.0, speed * np.cos(heading[:-1]) * np.diff(t)])
    u = np.full(n, 6000.0)
    rho = np.sqrt(e * e + nn * nn + u * u) + rng.normal(0, 40.0, n)
    az = (np.degrees(np.arctan2(e, nn)) + rng.normal(0, 0.12, n)) % 360.0
    el = np.degrees(np.arctan2(u, np.hypot(e, nn))) + rng.normal(0, 0.2, n)
    plots = np.stack([rho, az, el], -1)
    plots[rng.random(n) < 0.1] = np.nan
    plots[0] = [rho[0], az[0], el[0]]
    return t, plots


def _polar_csv(path, dt: float, jitter: float = 0.0, tracks: int = 3, n: int = 40):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["track_id", "t", "range", "azimuth", "elevation"])
        for k in range(tracks):
            t, plots = _flight(n, dt, k, jitter)
            for ti, p in zip(t, plots):
                w.writerow([f"trk{k}", repr(float(ti)), *("" if np.isnan(v) else repr(float(v)) for v in p)])
    return path


def _cartesian_csv(path, dt: float, tracks: int = 3, n: int = 40):
    from immnet.data.radar import converted

    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["track_id", "t", "x", "y", "z"])
        for k in range(tracks):
            t, plots = _flight(n, dt, k)
            xyz = np.full((n, 3), np.nan)
            seen = ~np.isnan(plots).any(-1)
            az, el = np.radians(plots[seen, 1]), np.radians(plots[seen, 2])
            rho = plots[seen, 0]
            xyz[seen] = np.stack([rho * np.cos(el) * np.sin(az), rho * np.cos(el) * np.cos(az), rho * np.sin(el)], -1)
            for ti, p in zip(t, xyz):
                w.writerow([f"trk{k}", repr(float(ti)), *("" if np.isnan(v) else repr(float(v)) for v in p)])
    return path


@pytest.mark.parametrize("dt, jitter, network", [(5.0, 0.5, "immnet-radar-5s"), (11.0, 1.0, "immnet-radar-11s")])
def test_plots_are_tracked_by_their_bands_radar_network(tmp_path, capsys, dt, jitter, network):
    src = _polar_csv(tmp_path / "plots.csv", dt, jitter)
    assert main(["track", "--input", str(src), "--output", str(tmp_path / "default.csv"), *SIGMAS]) == 0
    err = capsys.readouterr().err
    assert f"tracked by {network}, the shipped network told each plot's covariance" in err
    assert f"rows with {network} -> " in err
    assert "the bank" not in err
    assert main(["track", "--input", str(src), "--output", str(tmp_path / "method.csv"), *SIGMAS,
                 "--method", network]) == 0
    assert (tmp_path / "default.csv").read_bytes() == (tmp_path / "method.csv").read_bytes()
    assert main(["track", "--input", str(src), "--output", str(tmp_path / "bank.csv"), *SIGMAS,
                 "--weights", "bank"]) == 0
    assert (tmp_path / "default.csv").read_bytes() != (tmp_path / "bank.csv").read_bytes()


def test_covariance_columns_are_tracked_by_the_radar_network_told_them(tmp_path, capsys):
    from immnet.data.csvio import read_tracks_csv

    src = _polar_csv(tmp_path / "plots.csv", 5.0, 0.5)
    rows = read_tracks_csv(src, (40.0, 0.12, 0.2))
    with open(tmp_path / "cov.csv", "w", newline="") as f:  # the same plots as converted positions and covariances
        w = csv.writer(f)
        w.writerow(["track_id", "t", "x", "y", "z", "r_xx", "r_xy", "r_xz", "r_yy", "r_yz", "r_zz"])
        for tid, t, z, c in zip(rows.ids, rows.t, rows.z, rows.cov):
            cells = [] if np.isnan(z).any() else [*z, *(c[i, j] for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)))]
            w.writerow([tid, t, *(repr(float(v)) for v in cells)] + [""] * (9 - len(cells)))
    assert main(["track", "--input", str(tmp_path / "cov.csv"), "--output", str(tmp_path / "a.csv")]) == 0
    assert "tracked by immnet-radar-5s" in capsys.readouterr().err
    assert main(["track", "--input", str(tmp_path / "cov.csv"), "--output", str(tmp_path / "b.csv"),
                 "--method", "immnet-radar-5s"]) == 0
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()


def test_cartesian_rows_without_covariance_are_the_banks_as_before(tmp_path, capsys):
    src = _cartesian_csv(tmp_path / "xyz.csv", 5.0)
    assert main(["track", "--input", str(src), "--output", str(tmp_path / "default.csv")]) == 0
    err = capsys.readouterr().err
    assert "with the bank -> " in err and "immnet-radar" not in err
    assert main(["track", "--input", str(src), "--output", str(tmp_path / "bank.csv"), "--weights", "bank"]) == 0
    assert (tmp_path / "default.csv").read_bytes() == (tmp_path / "bank.csv").read_bytes()


def test_plots_between_the_bands_are_tracked_by_the_nearer_bands_filter(tmp_path, capsys):
    src = _polar_csv(tmp_path / "plots.csv", 8.0)  # 8 s: 2.5 s above 4.5-5.5, 2 s below 10-12
    assert main(["track", "--input", str(src), "--output", str(tmp_path / "default.csv"), *SIGMAS]) == 0
    err = capsys.readouterr().err
    assert ("median scan interval is 8 s, whose scans the shipped radar networks (4.5-5.5 s, 10-12 s) were not "
            "trained at: tracked by radar-imm-robust-11s") in err
    assert main(["track", "--input", str(src), "--output", str(tmp_path / "method.csv"), *SIGMAS,
                 "--method", "radar-imm-robust-11s"]) == 0
    assert (tmp_path / "default.csv").read_bytes() == (tmp_path / "method.csv").read_bytes()


@pytest.mark.parametrize("intervals, chosen", [
    ([5.0] * 9, "immnet-radar-5s"),
    ([4.5, 5.5, 5.0, 10.0, 5.2], "immnet-radar-5s"),  # 10 s: two scans of 5, one missed
    ([11.0, 10.0, 22.0, 12.0], "immnet-radar-11s"),  # 22 s: two of 11
    ([5.0, 5.0, 4.0], "radar-imm-robust-5s"),  # 4 s: shorter than the band, which the network was not trained at
    ([5.0, 5.0, 7.0], "radar-imm-robust-5s"),  # 7 s: two of 3.5 s
    ([7.7] * 3, "radar-imm-robust-5s"),  # 2.2 s from 4.5-5.5, 2.3 s from 10-12
    ([7.8] * 3, "radar-imm-robust-11s"),
    ([1.0] * 5, "radar-imm-robust-5s"),
    ([20.0, 30.0, 15.0], "radar-imm-robust-11s"),  # 15 s: 2 of 7.5
])
def test_the_choice_by_scan_interval(intervals, chosen):
    assert radar_default(np.array(intervals))[0] == chosen
    assert [b[2] for b in RADAR_BANDS] == [(4.5, 5.5), (10.0, 12.0)]


def test_options_the_radar_default_has_not_are_refused_in_one_line(tmp_path, capsys):
    src = _polar_csv(tmp_path / "plots.csv", 5.0, 0.5)
    out = tmp_path / "o.csv"
    for extra, message in (
            (["--adapt"], "immnet track: error: --adapt is the bank's and the shipped networks' option; these rows "
                          "carry each detection's covariance and are tracked by immnet-radar-5s by default, which has "
                          "none: give --weights bank to track them with the bank"),
            (["--r", "30"], "immnet track: error: --r and the CSV's plots both give the measurement noise of "
                            "immnet-radar-5s (the default for rows with covariances): give one of the two")):
        assert main(["track", "--input", str(src), "--output", str(out), *SIGMAS, *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert err.endswith(message) and "\n" not in err
        assert not out.exists()


def test_the_shipped_radar_weights_by_name_are_told_the_rows_covariances(tmp_path, capsys):
    src = _polar_csv(tmp_path / "plots.csv", 5.0, 0.5)
    assert main(["track", "--input", str(src), "--output", str(tmp_path / "w.csv"), *SIGMAS,
                 "--weights", "radar-5s"]) == 0
    assert "not used" not in capsys.readouterr().err
    assert main(["track", "--input", str(src), "--output", str(tmp_path / "m.csv"), *SIGMAS,
                 "--method", "immnet-radar-5s"]) == 0
    assert (tmp_path / "w.csv").read_bytes() == (tmp_path / "m.csv").read_bytes()
    capsys.readouterr()
    # a CSV without covariances gives it none: refused by name
    xyz = _cartesian_csv(tmp_path / "xyz.csv", 5.0)
    assert main(["track", "--input", str(xyz), "--output", str(tmp_path / "x.csv"), "--weights", "radar-5s"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith("is told each detection's covariance, which this CSV does not hold: give the columns "
                        "r_xx..r_zz, a radar's plots with their stds, or one std for all with --r METRES")
    assert "\n" not in err and not (tmp_path / "x.csv").exists()


def test_a_track_of_one_plot_is_tracked_by_the_radar_network(tmp_path, capsys):
    """A segment of one row is padded at an interval inside the network's range (it was 1 s, which the network
    refuses): the lone plot's row is its converted position, the track starting there."""
    from immnet.data.csvio import read_tracks_csv

    src = _polar_csv(tmp_path / "plots.csv", 5.0, 0.5)
    with open(src, "a") as f:
        f.write("lone,3.0,30000.0,40.0,10.0\n")
    out = tmp_path / "o.csv"
    assert main(["track", "--input", str(src), "--output", str(out), *SIGMAS]) == 0
    assert "rows with immnet-radar-5s -> " in capsys.readouterr().err
    rows = read_tracks_csv(src, (40.0, 0.12, 0.2))
    with open(out) as f:
        got = [r for r in csv.DictReader(f) if r["track_id"] == "lone"]
    assert len(got) == 1
    np.testing.assert_allclose([float(got[0][k]) for k in ("x", "y", "z")], rows.z[-1], rtol=0, atol=1e-5)


def test_the_note_names_the_interval_the_bands_network_refuses():
    """A track at the band's scans with one longer gap that missed scans cut below the band (7 s: two of 3.5 s) falls
    back to the filter; the note names that interval, not the shortest (5 s, inside the band) as "below" it."""
    method, line = radar_default(np.array([5.0, 5.0, 5.0, 7.0, 5.0]))
    assert method == "radar-imm-robust-5s"
    assert ("but an interval of 7 s, 2 scans of 3.5 s with missed scans, is below 4.5-5.5 s, where immnet-radar-5s "
            "was trained") in line
    assert "shortest" not in line
    method, line = radar_default(np.array([5.0, 5.0, 4.0, 5.0, np.nan]))
    assert "but their shortest, 4 s, is below 4.5-5.5 s, where immnet-radar-5s was trained" in line
