"""A radar's plots (issue 62): ``immnet track`` on range/azimuth/elevation CSVs and Cartesian CSVs with each detection's
covariance, ``Tracker.step(z, R=...)``, and ``immnet data adsb``'s plots, outliers, placement and ``meas_cov``."""

import csv
import warnings

import numpy as np
import pytest
import torch

from immnet import keys
from immnet.cli import main
from immnet.data import adsb, radar
from immnet.data.csvio import read_tracks_csv
from tiny_runs import write_csv

SIGMAS = ("--sigma-range", "30", "--sigma-azimuth", "0.1", "--sigma-elevation", "0.2")
TINY = (1e-9, 1e-9, 1e-9)
"""Stds so small that a converted plot is its exact conversion (a debiased conversion differs by O(std^2))."""


def _enu_track() -> np.ndarray:
    """A target 50 km north of the radar crossing north, x from -500 to +500 m, climbing: azimuths 359.4 ... 0.6."""
    k = np.arange(11.0)
    return np.stack([-500.0 + 100.0 * k, 50_000.0 + 10.0 * k, 3000.0 + 2.0 * k], -1)


def _plots(enu: np.ndarray) -> np.ndarray:
    """Range (m), azimuth (degrees in [0, 360)), elevation (degrees) of ENU points, computed here."""
    e, n, u = enu[:, 0], enu[:, 1], enu[:, 2]
    return np.stack([np.sqrt(e * e + n * n + u * u), np.degrees(np.arctan2(e, n)) % 360.0,
                     np.degrees(np.arctan2(u, np.hypot(e, n)))], -1)


def _polar_rows(plots, tid="a", sigmas=None):
    return [[tid, repr(float(k)), *("" if np.isnan(v) else repr(float(v)) for v in p), *(repr(float(s)) for s in sigmas or ())]
            for k, p in enumerate(plots)]


def _jacobian(rho, az, el) -> np.ndarray:
    """d(e, n, u) / d(rho, az, el) by central differences of the conversion written out here."""
    def enu(p):
        return np.array([p[0] * np.cos(p[2]) * np.sin(p[1]), p[0] * np.cos(p[2]) * np.cos(p[1]), p[0] * np.sin(p[2])])
    p, h = np.array([rho, az, el]), np.array([1e-3, 1e-9, 1e-9])
    return np.stack([(enu(p + h[i] * np.eye(3)[i]) - enu(p - h[i] * np.eye(3)[i])) / (2 * h[i]) for i in range(3)], -1)


# --- reading plots -------------------------------------------------------------------------------------------------
def test_plots_come_back_to_their_positions_across_north(tmp_path):
    enu = _enu_track()
    plots = _plots(enu)
    assert plots[0, 1] > 359 and plots[-1, 1] < 1  # the target crosses north
    plots[7, 1] -= 360.0  # azimuths of any finite value are wrapped: -359.x is 0.x
    plots[3] = np.nan  # an empty range, azimuth, elevation is a missed detection
    rows = read_tracks_csv(write_csv(tmp_path / "p.csv", ["track_id", "t", "range", "azimuth", "elevation"],
                                  _polar_rows(plots)), TINY)
    want = enu.copy()
    want[3] = np.nan
    assert rows.polar and rows.z.dtype == np.float64
    np.testing.assert_allclose(rows.z, want, atol=1e-6, rtol=0)
    assert np.isnan(rows.cov[3]).all() and np.isfinite(rows.cov[[0, 1, 2, 4]]).all()


def test_the_cli_tracks_plots_in_the_radars_frame(tmp_path, capsys):
    enu = _enu_track()
    src = write_csv(tmp_path / "p.csv", ["track_id", "t", "range", "azimuth", "elevation"], _polar_rows(_plots(enu)))
    out = tmp_path / "o.csv"
    assert main(["track", "--input", str(src), "--output", str(out), "--method", "imm-tuned",
                 "--sigma-range", "1e-9", "--sigma-azimuth", "1e-9", "--sigma-elevation", "1e-9"]) == 0
    with open(out, newline="") as f:
        first = next(csv.DictReader(f))
    # imm-tuned starts a track at its first measurement: the plot's east-north-up position
    np.testing.assert_allclose([float(first[c]) for c in "xyz"], enu[0], atol=1e-6)
    assert "imm-tuned assumes its own measurement noise" in capsys.readouterr().err


def test_per_row_stds_are_the_options_and_the_covariance_is_the_conversions(tmp_path):
    plots = _plots(_enu_track())
    header = ["track_id", "t", "range", "azimuth", "elevation"]
    by_option = read_tracks_csv(write_csv(tmp_path / "a.csv", header, _polar_rows(plots)), (30.0, 0.1, 0.2))
    per_row = read_tracks_csv(write_csv(tmp_path / "b.csv", header + ["sigma_range", "sigma_azimuth", "sigma_elevation"],
                                     _polar_rows(plots, sigmas=(30.0, 0.1, 0.2))))
    np.testing.assert_array_equal(per_row.z, by_option.z)
    np.testing.assert_array_equal(per_row.cov, by_option.cov)
    stds = np.array([[20.0 + k, 0.05 + 0.01 * k, 0.1 + 0.02 * k] for k in range(len(plots))])
    rows = [["a", repr(float(k)), *_polar_rows(plots[k : k + 1], sigmas=tuple(stds[k]))[0][2:]]
            for k in range(len(plots))]
    varied = read_tracks_csv(write_csv(tmp_path / "c.csv", header + ["sigma_range", "sigma_azimuth", "sigma_elevation"],
                                    rows))
    for k, (rho, az, el) in enumerate(plots):
        J = _jacobian(rho, np.radians(az), np.radians(el))
        want = J @ np.diag([stds[k, 0] ** 2, *np.radians(stds[k, 1:]) ** 2]) @ J.T
        np.testing.assert_allclose(varied.cov[k], want, rtol=1e-3, atol=1e-3 * want.max())  # first order: O(std^2)


HEAD = "track_id,t,range,azimuth,elevation"
REFUSALS = [
    ("track_id,t,x,y,z,range,azimuth,elevation\na,0,1,2,3,4,5,6\n", (),
     "line 1: columns x,y,z,range,azimuth,elevation mix Cartesian (x,y,z) and polar (range,azimuth,elevation) "
     "positions: give one of the two"),
    ("track_id,t,x,y,z,sigma_range,sigma_azimuth,sigma_elevation\na,0,1,2,3,4,5,6\n", (),
     "line 1: column(s) sigma_range,sigma_azimuth,sigma_elevation are the range,azimuth,elevation rows' stds, not for "
     "x,y,z rows"),
    (HEAD + ",r_xx\na,0,1e4,1,1,1\n", SIGMAS,
     "line 1: column(s) r_xx are the x,y,z rows' covariance, not for range,azimuth,elevation rows"),
    (HEAD + ",sigma_range,sigma_azimuth\na,0,1e4,1,1,1,1\n", (),
     "line 1: missing column(s) sigma_elevation (the columns sigma_range,sigma_azimuth,sigma_elevation go together)"),
    (HEAD + ",sigma_range,sigma_azimuth,sigma_elevation\na,0,1e4,1,1,-5,0.1,0.1\n", (),
     "line 2: column 'sigma_range' is -5: a detection's standard deviation is a finite number > 0"),
    (HEAD + ",sigma_range,sigma_azimuth,sigma_elevation\na,0,1e4,1,1,30,,0.1\n", (),
     "line 2: column 'sigma_azimuth' is empty: a detection's standard deviation is a finite number > 0"),
    (HEAD + "\na,0,1e4,1,1\n", ("--sigma-range", "30", "--sigma-azimuth", "0", "--sigma-elevation", "0.2"),
     "--sigma-azimuth is a standard deviation, a finite number > 0; got 0"),
    (HEAD + "\na,0,1e4,1,1\n", ("--sigma-range", "30", "--sigma-azimuth", "0.1"),
     "the radar's stds are three numbers: give --sigma-elevation too (--sigma-range METRES --sigma-azimuth DEG "
     "--sigma-elevation DEG)"),
    (HEAD + "\na,0,0,1,1\n", SIGMAS, "line 2: column 'range' is 0: a slant range is > 0 (m)"),
    (HEAD + "\na,0,1e4,1,1\na,1,-3,1,1\n", SIGMAS, "line 3: column 'range' is -3: a slant range is > 0 (m)"),
    (HEAD + "\na,0,1e4,1,91\n", SIGMAS, "line 2: column 'elevation' is 91: an elevation lies in [-90, 90] degrees"),
    (HEAD + "\na,0,1e4,inf,1\n", SIGMAS, "line 2: column 'azimuth' is inf: an azimuth is a finite number of degrees"),
    (HEAD + ",sigma_range,sigma_azimuth,sigma_elevation\na,0,1e4,1,1,30,0.1,0.2\n", SIGMAS,
     "line 1: columns sigma_range,sigma_azimuth,sigma_elevation and the options --sigma-range, --sigma-azimuth, "
     "--sigma-elevation both give the radar's stds: give one of the two"),
    (HEAD + "\na,0,1e4,1,1\n", (),
     "line 1: range,azimuth,elevation rows need the radar's stds: give --sigma-range METRES --sigma-azimuth DEG "
     "--sigma-elevation DEG, or the columns sigma_range,sigma_azimuth,sigma_elevation"),
    ("track_id,t,x,y,z\na,0,1,2,3\n", SIGMAS,
     "--sigma-range, --sigma-azimuth, --sigma-elevation are the stds of range,azimuth,elevation rows; this CSV has "
     "x,y,z (each row's covariance: the columns r_xx,r_xy,r_xz,r_yy,r_yz,r_zz)"),
    ("track_id,t,x,y,z,r_xx,r_xy,r_xz,r_yy,r_yz,r_zz\na,0,1,2,3,4,5,0,4,0,4\n", (),
     "line 2: columns r_xx,r_xy,r_xz,r_yy,r_yz,r_zz are not a positive-definite covariance (eigenvalues -1, 4, 9 m^2)"),
    ("track_id,t,x,y,z,r_xx,r_xy,r_xz,r_yy,r_yz,r_zz\na,0,1,2,3,,0,0,4,0,4\n", (),
     "line 2: column 'r_xx' is empty: a detection's covariance entries are finite numbers (m^2)"),
    ("track_id,t,x,y,z,r_xx,r_yy\na,0,1,2,3,4,4\n", (),
     "line 1: missing column(s) r_xy, r_xz, r_yz, r_zz (the columns r_xx,r_xy,r_xz,r_yy,r_yz,r_zz go together)"),
]


@pytest.mark.parametrize("text, options, message", REFUSALS)
def test_each_bad_input_is_one_line_and_no_output(tmp_path, capsys, text, options, message):
    (tmp_path / "in.csv").write_text(text)
    out = tmp_path / "o.csv"
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(out), "--method", "imm-tuned",
                 *options]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == f"immnet track: error: {message}"
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["in.csv"]


def test_stds_for_an_npz_are_refused(tmp_path, capsys):
    np.savez(tmp_path / "in.npz", measurements=np.zeros((1, 3, 3)))
    assert main(["track", "--input", str(tmp_path / "in.npz"), "--output", str(tmp_path / "o.npz"), *SIGMAS]) == 2
    assert capsys.readouterr().err.strip().endswith(
        f"--sigma-range, --sigma-azimuth, --sigma-elevation are the stds of a CSV of plots (range,azimuth,elevation); "
        f"{tmp_path / 'in.npz'} is not a CSV")


# --- each detection's covariance in a method's batch ---------------------------------------------------------------
class _Reading:
    """imm-tuned, made to read ``meas_cov`` (as a filter told each detection's covariance does), keeping its batches."""

    def __init__(self, inner):
        self.inner, self.name, self.batches = inner, "reading", []
        self.needs = (*inner.needs, keys.MEAS_COV)

    def track(self, batch):
        self.batches.append(batch.clone())
        return self.inner.track(batch)


@pytest.fixture
def reading(monkeypatch):
    from immnet.filters import methods

    built = []
    original = methods.build_method

    def build(name, *args, **kwargs):
        built.append(_Reading(original("imm-tuned", *args, **kwargs)) if name == "reading" else
                     original(name, *args, **kwargs))
        return built[-1]

    monkeypatch.setattr(methods, "build_method", build)
    monkeypatch.setattr(methods, "gives_cov", lambda name, *a: True)
    return built


def _cartesian(tmp_path, name, enu, cov=None):
    header = ["track_id", "t", "x", "y", "z"] + (["r_xx", "r_xy", "r_xz", "r_yy", "r_yz", "r_zz"] if cov is not None
                                                 else [])
    rows = []
    for k, p in enumerate(enu):
        extra = [] if cov is None else ["" if np.isnan(p).any() else repr(float(cov[k][i, j]))
                                        for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))]
        rows.append(["a", repr(float(k)), *("" if np.isnan(v) else repr(float(v)) for v in p), *extra])
    return write_csv(tmp_path / name, header, rows)


def test_each_rows_covariance_reaches_the_batch(tmp_path, reading):
    enu = _enu_track()
    enu[4] = np.nan
    rng = np.random.default_rng(0)
    A = rng.normal(size=(len(enu), 3, 3))
    cov = A @ np.swapaxes(A, -1, -2) + np.eye(3)
    src = _cartesian(tmp_path, "c.csv", enu, cov)
    assert main(["track", "--input", str(src), "--output", str(tmp_path / "o.csv"), "--method", "reading"]) == 0
    (batch,) = reading[0].batches
    got = batch[keys.MEAS_COV][0].numpy()
    want = cov.copy()
    want[4] = np.nan
    np.testing.assert_array_equal(got[: len(enu)], want)


def test_a_covariance_of_r2_i_is_the_plain_csv_with_r(tmp_path, reading, capsys):
    enu = _enu_track()
    enu[6] = np.nan
    r = 7.5
    plain = _cartesian(tmp_path, "plain.csv", enu)
    with_cov = _cartesian(tmp_path, "cov.csv", enu, np.broadcast_to(r * r * np.eye(3), (len(enu), 3, 3)))
    assert main(["track", "--input", str(plain), "--output", str(tmp_path / "a.csv"), "--method", "reading",
                 "--r", str(r)]) == 0
    assert main(["track", "--input", str(with_cov), "--output", str(tmp_path / "b.csv"), "--method", "reading"]) == 0
    a, b = reading[0].batches[0], reading[1].batches[0]
    assert sorted(a.keys()) == sorted([*b.keys(), keys.R])  # and --r as every track's r, for a method told it
    for key in b.keys():
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, equal_nan=True)
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()
    # both at once, or a method that reads it with neither, is refused
    assert main(["track", "--input", str(with_cov), "--output", str(tmp_path / "c.csv"), "--method", "reading",
                 "--r", str(r)]) == 2
    assert capsys.readouterr().err.strip().endswith(
        "immnet track: error: --r and the CSV's covariance columns both give the measurement noise of --method reading: "
        "give one of the two")
    assert main(["track", "--input", str(plain), "--output", str(tmp_path / "c.csv"), "--method", "reading"]) == 2
    assert capsys.readouterr().err.strip().endswith(
        "immnet track: error: --method reading is told each detection's covariance, which this CSV does not hold: give "
        "the columns r_xx..r_zz, a radar's plots with their stds, or one std for all with --r METRES")


def test_a_method_that_assumes_its_noise_tracks_the_same_and_says_so(tmp_path, capsys):
    enu = _enu_track()
    plain = _cartesian(tmp_path, "plain.csv", enu)
    with_cov = _cartesian(tmp_path, "cov.csv", enu, np.broadcast_to(4.0 * np.eye(3), (len(enu), 3, 3)))
    for src, out in ((plain, "a.csv"), (with_cov, "b.csv")):
        assert main(["track", "--input", str(src), "--output", str(tmp_path / out), "--method", "imm-tuned"]) == 0
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()
    assert "imm-tuned assumes its own measurement noise: each detection's covariance from the CSV is not used" in \
        capsys.readouterr().err


# --- Tracker.step(z, R=...) ----------------------------------------------------------------------------------------
def test_tracker_step_checks_r_and_says_it_is_unused():
    from immnet.tracking import Tracker

    z = torch.tensor([[1000.0, 2000.0, 300.0], [float("nan")] * 3], dtype=torch.float64)
    good = torch.stack([torch.eye(3, dtype=torch.float64) * 25, torch.full((3, 3), float("nan"), dtype=torch.float64)])
    a, b = Tracker.pretrained("general"), Tracker.pretrained("general")
    with pytest.warns(UserWarning, match="this network does not use R"):
        out = a.step(z, R=good)
    torch.testing.assert_close(out[keys.FUSED], b.step(z)[keys.FUSED], equal_nan=True)
    with pytest.raises(ValueError, match=r"^R is each track's measurement covariance \[n_tracks, 3, 3\] = \[2, 3, 3\], "
                                         r"got \[3, 3\]$"):
        a.step(z, R=torch.eye(3))
    not_pd = good.clone()
    not_pd[0] = torch.tensor([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match=r"^R of track 0 is not a symmetric positive-definite covariance \(m\^2\)"):
            a.step(z, R=not_pd)


# --- immnet data adsb ----------------------------------------------------------------------------------------------
needs_samples = pytest.mark.skipif(adsb.samples_dir() is None, reason="traffic's sample files are not installed")
PLOTS = ("--sigma-range", "20,60", "--sigma-azimuth", "0.05,0.2", "--sigma-elevation", "0.1,0.3")


def _adsb(out, *options):
    assert main(["data", "adsb", "--samples", "collections/quickstart", "--out", str(out), "--T", "60", "--dt", "5",
                 "--p-miss", "0.1", "--max-flights", "60", "--splits", "all-test", "--quiet", *options]) == 0
    from immnet.data.storage import load_dataset

    return load_dataset(out / "test")


def _nis(td):
    z, p = td[keys.MEASUREMENTS].double().numpy(), td[keys.STATES].double().numpy()[..., [0, 3, 6]]
    cov = td[keys.MEAS_COV].double().numpy()
    seen = ~np.isnan(z).any(-1)
    e = (z - p)[seen]
    return np.einsum("ni,nij,nj->n", e, np.linalg.inv(cov[seen]), e), seen


@needs_samples
def test_adsb_plots_are_placed_10_to_150_km_away_with_their_covariance(tmp_path):
    td, meta = _adsb(tmp_path / "plots", *PLOTS, "--range-km", "10,150")
    assert meta["params"]["range_km"] == [10.0, 150.0] and meta["site_from"].startswith("one radar per flight")
    p = td[keys.STATES].double().numpy()[..., [0, 3, 6]]
    rho, _, _ = radar.polar(p)
    assert 10e3 <= rho.min() and rho.max() <= 150e3
    z, cov = td[keys.MEASUREMENTS].double().numpy(), td[keys.MEAS_COV].double().numpy()
    seen = ~np.isnan(z).any(-1)
    assert np.isnan(cov[~seen]).all() and np.isfinite(cov[seen]).all()
    # each plot's covariance is J diag(s_rho^2, s_az^2, s_el^2) J^T at its measured position, one s per window, to the
    # unbiased conversion's second-order terms (immnet.data.radar.converted: a few per cent at 150 km and these stds)
    m_rho, m_az, m_el = radar.polar(z[seen])
    n_win = np.nonzero(seen)[0]
    D = np.array([np.linalg.solve(J, np.linalg.solve(J, C).T) for J, C in
                  zip((_jacobian(*a) for a in zip(m_rho, m_az, m_el)), cov[seen])])
    d = np.diagonal(D, axis1=1, axis2=2)
    off = D - d[:, :, None] * np.eye(3)
    assert np.abs(off).max() <= 1e-3 * d.max(1).min()
    s = np.sqrt(d) * np.array([1.0, 180 / np.pi, 180 / np.pi])
    lo, hi = np.array([20, 0.05, 0.1]), np.array([60, 0.2, 0.3])
    assert (s >= lo * (1 - 3e-2)).all() and (s <= hi * (1 + 3e-2)).all()
    for w in np.unique(n_win):  # one draw per window
        np.testing.assert_allclose(s[n_win == w], np.broadcast_to(s[n_win == w][0], s[n_win == w].shape), rtol=3e-2)
    # without outliers the errors are what the covariances say: NIS ~ chi^2_3 (mean 3)
    nis, _ = _nis(td)
    assert len(nis) > 2000 and 2.8 < nis.mean() < 3.2


@needs_samples
@pytest.mark.parametrize("kind", ["plots", "cartesian"])
def test_adsb_outliers_are_their_share_and_keep_the_radars_covariance(tmp_path, kind):
    share, scale = 0.05, 10.0
    td, meta = _adsb(tmp_path / kind, *(PLOTS if kind == "plots" else ()), "--outliers", str(share),
                     "--outlier-scale", str(scale))
    assert meta["params"]["outliers"] == share
    nis, seen = _nis(td)
    # an outlier's NIS is scale^2 chi^2_3: beyond chi^2_3's 0.9999 quantile (21.108) but with P(chi^2_3 < 0.21108)
    from scipy.stats import chi2

    q = chi2.ppf(0.9999, 3)
    p = share * chi2.sf(q / scale**2, 3) + (1 - share) * 1e-4
    n = len(nis)
    assert abs((nis > q).mean() - p) < 4 * np.sqrt(p * (1 - p) / n)
    if kind == "cartesian":  # 3D-LAST's noise: each detection's covariance r^2 I
        r = td[keys.R].double().numpy()
        want = (r**2)[:, None, None, None] * np.eye(3)
        cov = td[keys.MEAS_COV].double().numpy()
        np.testing.assert_allclose(cov[seen], np.broadcast_to(want, cov.shape)[seen], rtol=1e-6)
