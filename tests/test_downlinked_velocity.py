"""``scripts/downlinked_velocity.py`` (docs/notebook/real-flights.md "Told the aircraft's velocity"): a report turned
into the radar's frame against the geodesy's positions, the filter told a late velocity against FilterPy, the reports of
a rebuilt real-flight set against its truth, and the script's rows against the filters run here."""

import json
import math
import runpy

import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter

from immnet import keys
from immnet.config import REPO_ROOT, load_yaml
from immnet.data import adsb, real
from immnet.data.geodesy import enu_to_geodetic, geodetic_to_enu
from immnet.data.storage import as_batch, load_dataset, tensor_files, write_dataset
from immnet.filters.methods import build_method, method_config
from immnet.evaluation.search import states_rmse
from immnet.filters.imm import ACC_STD, VEL_STD
from tests.test_data_adsb import SMALL, T0, _track, _write
from tests.tiny_runs import TINY

SCRIPT = REPO_ROOT / "scripts" / "downlinked_velocity.py"
SITE = (48.9, 2.45, 0.0)


@pytest.fixture(scope="module")
def dv():
    return runpy.run_path(str(SCRIPT))


def test_a_report_in_the_radars_frame_is_the_motion_of_its_positions(dv):
    """Ground speed, track and vertical rate reported 150 km from the site: the site-frame velocity equals the
    difference of the aircraft's positions a short time apart, each taken through the geodesy (geodetic -> the
    site's ENU), moved along its own east-north-up frame."""
    lat, lon, h = 49.8, 4.3, 10_000.0
    speed, track, climb = 230.0, 60.0, 8.0
    ours = dv["site_velocity"](np.array([speed]), np.array([track]), np.array([climb]), np.array([lat]),
                               np.array([lon]), SITE)[0]
    chi, dt = math.radians(track), 0.01
    local = np.array([speed * math.sin(chi), speed * math.cos(chi), climb])
    ends = [enu_to_geodetic(s * dt * local, (lat, lon, h)) for s in (-1, 1)]
    pos = [geodetic_to_enu(*e, SITE) for e in ends]
    np.testing.assert_allclose(ours, (pos[1] - pos[0]) / (2 * dt), atol=1e-3)
    assert abs(ours[2] - climb) > 1.0  # the site's up is not the aircraft's: the frames turn over 150 km
    np.testing.assert_allclose(np.linalg.norm(ours), np.linalg.norm(local), rtol=1e-12)


def test_the_latest_report_no_older_than_max_age(dv):
    times = np.array([10.0, 11.0, 15.0])
    values = np.arange(9.0).reshape(3, 3)
    got = dv["latest"](times, values, np.array([9.0, 10.0, 10.5, 13.9, 14.1, 15.0, 30.0]), 3.0)
    np.testing.assert_array_equal(got[:, 0], [np.nan, 0, 0, 3, np.nan, 6, np.nan])
    assert np.isnan(dv["latest"](times[:0], values[:0], np.array([1.0]), 3.0)).all()


def _one_model_ca(sigma_q: float) -> dict:
    return {"class_path": "immnet.filters.per_axis.PerAxisIMMTracker",
            "init_args": {"name": "ca", "r": "data", "sigma_q": [sigma_q],
                          "model_set": {"models": [{"class_path": "immnet.motion.ConstantAcceleration",
                                                    "init_args": {"noise": "continuous"}}]}}}


def test_the_filter_told_a_late_velocity_is_filterpys(tmp_path, dv):
    """A decoupled one-model CA IMM told each axis's velocity ``L`` s late: per axis, FilterPy's KalmanFilter with
    ``z = (p, v)``, ``H = [[1, 0, 0], [0, 1, -L]]``, ``R = diag(r^2, s^2)``, the closed-form white-jerk ``F`` and ``Q``,
    the position alone where a scan has no report; from the package's start at the first detection."""
    batch = as_batch(load_dataset(write_dataset(tmp_path / "d", 3, seed=4, spec=TINY))[0], torch.float64)
    B, T = batch[keys.MEASUREMENTS].shape[:2]
    g = torch.Generator().manual_seed(0)
    reports = batch[keys.STATES][..., [1, 4, 7]] + torch.randn(B, T, 3, generator=g, dtype=torch.float64)
    reports[torch.rand(B, T, 3, generator=g) < 0.3] = float("nan")
    sq, lag, sigma = 0.7, 1.5, (2.0, 0.5)
    ours = dv["told_velocity"](dv["decoupled"](_one_model_ca(sq)), batch, reports, sigma, lag)[keys.STATE].double()
    dts = torch.diff(batch[keys.TIME].double(), dim=1)
    for b in range(B):
        z = batch[keys.MEASUREMENTS][b].double().numpy()
        r = float(batch[keys.R][b])
        start = int(np.isfinite(z).all(-1).nonzero()[0][0])
        for a in range(3):
            kf = KalmanFilter(dim_x=3, dim_z=2)
            kf.x = np.array([z[start, a], 0.0, 0.0])
            kf.P = np.diag([r * r, VEL_STD**2, ACC_STD**2])
            np.testing.assert_allclose(ours[b, start, 3 * a : 3 * a + 3].numpy(), kf.x, atol=1e-9)
            for t in range(start + 1, T):
                h = float(dts[b, t - 1])
                F = np.array([[1, h, h * h / 2], [0, 1, h], [0, 0, 1]])
                Q = sq**2 * np.array([[h**5 / 20, h**4 / 8, h**3 / 6], [h**4 / 8, h**3 / 3, h**2 / 2],
                                      [h**3 / 6, h**2 / 2, h]])
                kf.predict(F=F, Q=Q)
                v = float(reports[b, t, a])
                if np.isfinite(z[t, a]) and math.isfinite(v):
                    s2 = sigma[0 if a < 2 else 1] ** 2
                    kf.update(np.array([z[t, a], v]), R=np.diag([r * r, s2]), H=np.array([[1, 0, 0], [0, 1, -lag]]))
                elif np.isfinite(z[t, a]):
                    kf.update(np.array([z[t, a]]), R=np.array([[r * r]]), H=np.array([[1.0, 0, 0]]))
                np.testing.assert_allclose(ours[b, t, 3 * a : 3 * a + 3].numpy(), kf.x, atol=1e-6, rtol=1e-9)
    # told nothing, it is the tracker itself
    none = torch.full_like(reports, float("nan"))
    plain = dv["decoupled"](_one_model_ca(sq)).track(batch)[keys.STATE].double()
    torch.testing.assert_close(dv["told_velocity"](dv["decoupled"](_one_model_ca(sq)), batch, none, sigma, lag)[
        keys.STATE].double(), plain, rtol=0, atol=1e-6)


def test_a_joint_filter_told_each_plots_covariance_and_a_late_velocity_is_filterpys(tmp_path, dv):
    """A joint one-model CA IMM told each plot's covariance ``R_p`` (``r: detection``) and the velocity ``L`` s late:
    FilterPy's KalmanFilter of the 9-D state with ``z = (p, v)``, ``H`` the positions' rows and ``[0, 1, -L]`` per axis,
    ``R = blockdiag(R_p, diag(s^2))``, the velocity's rows at a variance of ``NO_REPORT`` where a scan has no report;
    from the package's start at the first detection. Told no report at all, it is the IMM itself."""
    batch = as_batch(load_dataset(write_dataset(tmp_path / "d", 3, seed=4, spec=TINY))[0], torch.float64)
    B, T = batch[keys.MEASUREMENTS].shape[:2]
    g = torch.Generator().manual_seed(1)
    A = torch.randn(B, T, 3, 3, generator=g, dtype=torch.float64) * 3.0
    batch[keys.MEAS_COV] = A @ A.transpose(-1, -2) + 4.0 * torch.eye(3, dtype=torch.float64)  # anisotropic, per plot
    reports = batch[keys.STATES][..., [1, 4, 7]] + torch.randn(B, T, 3, generator=g, dtype=torch.float64)
    reports[torch.rand(B, T, 3, generator=g) < 0.3] = float("nan")
    sq, lag, sigma = 0.7, 1.5, (2.0, 0.5)
    config = {"class_path": "immnet.filters.IMMTracker",
              "init_args": {"name": "ca", "r": "detection", "sigma_q": [sq],
                            "model_set": {"models": [{"class_path": "immnet.motion.ConstantAcceleration",
                                                      "init_args": {"noise": "continuous"}}]}}}
    ours = dv["told_velocity"](dv["decoupled"](config), batch, reports, sigma, lag)[keys.STATE].double()
    dts = torch.diff(batch[keys.TIME].double(), dim=1)
    H = np.zeros((6, 9))
    for a in range(3):
        H[a, 3 * a], H[3 + a, 3 * a + 1], H[3 + a, 3 * a + 2] = 1.0, 1.0, -lag
    for b in range(B):
        z = batch[keys.MEASUREMENTS][b].double().numpy()
        R = batch[keys.MEAS_COV][b].numpy()
        start = int(np.isfinite(z).all(-1).nonzero()[0][0])
        kf = KalmanFilter(dim_x=9, dim_z=6)
        kf.x = ours[b, start].numpy().copy()  # the package's start: the first plot, its covariance R_p's block
        kf.P = np.diag(np.tile([0.0, VEL_STD**2, ACC_STD**2], 3))
        kf.P[np.ix_([0, 3, 6], [0, 3, 6])] = R[start]
        np.testing.assert_allclose(kf.x[[0, 3, 6]], z[start], atol=1e-9)
        for t in range(start + 1, T):
            h = float(dts[b, t - 1])
            F1 = np.array([[1, h, h * h / 2], [0, 1, h], [0, 0, 1]])
            Q1 = sq**2 * np.array([[h**5 / 20, h**4 / 8, h**3 / 6], [h**4 / 8, h**3 / 3, h**2 / 2],
                                   [h**3 / 6, h**2 / 2, h]])
            kf.predict(F=np.kron(np.eye(3), F1), Q=np.kron(np.eye(3), Q1))
            if np.isfinite(z[t]).all():
                v = reports[b, t].numpy()
                Rt = np.zeros((6, 6))
                Rt[:3, :3] = R[t]
                Rt[3:, 3:] = np.diag([sigma[0] ** 2 if np.isfinite(v[a]) else dv["NO_REPORT"] for a in range(2)]
                                     + [sigma[1] ** 2 if np.isfinite(v[2]) else dv["NO_REPORT"]])
                kf.update(np.concatenate([z[t], np.nan_to_num(v)]), R=Rt, H=H)
            np.testing.assert_allclose(ours[b, t].numpy(), kf.x, atol=1e-5, rtol=1e-8)
    none = torch.full_like(reports, float("nan"))
    plain = dv["decoupled"](config).track(batch)[keys.STATE].double()
    torch.testing.assert_close(dv["told_velocity"](dv["decoupled"](config), batch, none, sigma, lag)[keys.STATE].double(),
                               plain, rtol=0, atol=1e-6)
    robust = {**config, "init_args": {**config["init_args"], "robust": 2.5}}
    with pytest.raises(ValueError, match="the plain one"):
        dv["told_velocity"](dv["decoupled"](robust), batch, reports, sigma, lag)


def _with_velocity(recs: list[dict]) -> list[dict]:
    """Each record with the velocity its aircraft reports: the central difference of its neighbours' positions in its
    own east-north-up frame (geodesy only), as ground speed (kt), track (deg) and vertical rate (ft/min)."""
    out = []
    by = {}
    for r in recs:
        by.setdefault(r["icao24"], []).append(r)
    for rows in by.values():
        lat = np.array([r["latitude"] for r in rows])
        lon = np.array([r["longitude"] for r in rows])
        h = np.array([r["h_true"] for r in rows])
        for i, r in enumerate(rows):
            a, b = max(i - 1, 0), min(i + 1, len(rows) - 1)
            d = (geodetic_to_enu(lat[b], lon[b], h[b], (lat[i], lon[i], h[i]))
                 - geodetic_to_enu(lat[a], lon[a], h[a], (lat[i], lon[i], h[i]))) / (b - a)
            out.append({**{k: v for k, v in r.items() if k != "h_true"},
                        "groundspeed": math.hypot(d[0], d[1]) / adsb.KNOT,
                        "track": math.degrees(math.atan2(d[0], d[1])) % 360, "vertical_rate": d[2] / adsb.FEET * 60})
    return out


def _sample(tmp_path) -> str:
    """``tests/test_data_adsb.py``'s six aircraft (turning, climbing 5 m/s), each row with its report, made from the
    heights before the altitude's 25 ft rounding."""
    rng = np.random.default_rng(0)
    recs = []
    for k in range(6):
        lat, lon, h = enu_to_geodetic(_track(k, 400, rng), SITE)
        recs += [{"timestamp": T0 + 1000 * i, "icao24": f"abc{k:03d}", "latitude": float(lat[i]),
                  "longitude": float(lon[i]), "altitude": 25.0 * round(h[i] / adsb.FEET / 25.0), "onground": False,
                  "h_true": float(h[i])} for i in range(400)]
    return _write(tmp_path / "v.json.gz", _with_velocity(recs))


def test_the_reports_of_a_rebuilt_set_are_its_truths_velocity(tmp_path, dv):
    """The windows of a real-flight set built again from its sample file: the reports at its scans follow its truth
    (central differences of 1 s positions against the smoother's velocity); a set whose stored windows differ, or a
    3D-LAST set, is refused by name."""
    meta = real.make_adsb(tmp_path / "s", [_sample(tmp_path)], SMALL, seed=2)
    td, _ = load_dataset(tmp_path / "s" / "test")
    reports, rows, samples = dv["set_reports"](tmp_path / "s" / "test")
    assert (rows == 1.0).all() and (samples == str(tmp_path / "v.json.gz")).all() and reports.shape == (meta["counts"]["windows"]["test"], SMALL.T, 3)
    h, v, share = dv["report_errors"](reports, td[keys.STATES].double().numpy(), 0.0)
    assert share == 1.0 and h < 1.0 and v < 0.5
    file, _, shape = tensor_files(tmp_path / "s" / "test" / "tensors")[0][keys.STATES]
    a = np.memmap(file, dtype=np.float32, mode="r+", shape=shape)
    a[0, 5, 0] += 1.0
    a.flush()
    del a
    with pytest.raises(ValueError, match="its windows are not the ones its sample files and parameters give now"):
        dv["set_reports"](tmp_path / "s" / "test")
    write_dataset(tmp_path / "last", 4, seed=1, spec=TINY)
    with pytest.raises(ValueError, match="not a real-flight set"):
        dv["set_reports"](tmp_path / "last")


def test_the_rows_are_the_filters_run_here(tmp_path, dv, capsys):
    real.make_adsb(tmp_path / "s", [_sample(tmp_path)], SMALL, seed=2)
    tune, data = tmp_path / "s" / "val", tmp_path / "s" / "test"
    out = tmp_path / "v.json"
    rc = dv["main"](["--tune", str(tune), "--data", str(data), "--imm", "real-imm-axis", "--baseline", "real-imm-axis",
                     "--lags", "0,1", "--scales", "1,0.5", "--factors", "1,2", "--by-sample", "--json", str(out)])
    assert rc == 0
    report = json.loads(out.read_text())
    rows = {r["row"]: r for r in report["rows"]}
    batch = as_batch(load_dataset(data)[0])
    baseline = states_rmse(build_method("real-imm-axis").track(batch)[keys.STATE], batch)
    assert rows["real-imm-axis"]["average"] == pytest.approx(baseline, rel=1e-9)
    every = rows["real-imm-axis told the reported velocity, every axis"]
    L, scale, k = (float(s.split()[-1].removeprefix("x")) for s in
                   every["setting"].replace(" s,", ",").split(", "))
    tune_b = as_batch(load_dataset(tune)[0])
    h, v, _ = dv["report_errors"](dv["set_reports"](tune).velocity, tune_b[keys.STATES].double().numpy(), L)
    again = dv["told_velocity"](dv["decoupled"](load_yaml(method_config("real-imm-axis"))).scaled(scale), batch,
                                torch.from_numpy(dv["set_reports"](data).velocity), (k * h, k * v), L)
    assert every["average"] == pytest.approx(states_rmse(again[keys.STATE], batch), rel=1e-9)
    assert every["sigma"] == pytest.approx([k * h, k * v])
    (one,) = report["per_sample"]  # one sample file: its rows are the set's
    assert one["windows"] == len(batch) and one["told"] == pytest.approx(every["average"], rel=1e-12)
    assert one["real-imm-axis"] == pytest.approx(baseline, rel=1e-9)
    tune_base = states_rmse(build_method("real-imm-axis").track(tune_b)[keys.STATE], tune_b)
    told = dv["told_velocity"](dv["decoupled"](load_yaml(method_config("real-imm-axis"))).scaled(scale), tune_b,
                               torch.from_numpy(dv["set_reports"](tune).velocity), (k * h, k * v), L)
    assert states_rmse(told[keys.STATE], tune_b) < 0.8 * tune_base  # where it was chosen, far ahead of positions alone
    assert {r["axes"] == [2] for r in report["rows"] if r["kind"] == "told"} == {True, False}
    assert "on --tune" in capsys.readouterr().err
    write_dataset(tmp_path / "last", 4, seed=1, spec=TINY)
    assert dv["main"](["--tune", str(tmp_path / "last"), "--data", str(data), "--imm", "real-imm-axis"]) == 2
    assert dv["main"](["--tune", str(tune), "--data", str(data), "--imm", "imm-ekf"]) == 2
    err = capsys.readouterr().err
    assert "not a real-flight set" in err and "decoupled IMM" in err
