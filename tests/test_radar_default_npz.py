"""The default tracker of an .npz that carries each detection's covariance (``meas_cov [N, T, 3, 3]``, as ``immnet data
adsb --sigma-*`` writes it): the choice of CSV rows with covariances (``immnet.tracking.advice.radar_default``), told
``meas_cov``; the shipped radar networks by name given it; an .npz without it tracked by the bank as before."""

import csv
import json

import numpy as np
import pytest

from immnet.cli import main
from immnet.data.radar import converted

SIGMA = (40.0, 0.12, 0.2)  # m, deg, deg


def _npz(path, dt: float, jitter: float = 0.0, tracks: int = 3, n: int = 30, cov: bool = True):
    """Targets 30-40 km from the radar in a slow turn at 200 m/s, seen every ``dt`` s (U[-jitter, jitter] added) with
    the radar's noise, one plot in ten missed: ``measurements`` the unbiased converted plots, ``meas_cov`` their
    covariances (NaN where missed), ``states`` the truth, ``t`` the scan times. Also returns the arrays."""
    rng = np.random.default_rng(7)
    z = np.full((tracks, n, 3), np.nan)
    R = np.full((tracks, n, 3, 3), np.nan)
    states = np.zeros((tracks, n, 9))
    times = np.zeros((tracks, n))
    for k in range(tracks):
        t = np.cumsum(np.r_[0.0, dt + rng.uniform(-jitter, jitter, n - 1)])
        heading = np.radians(30.0 + 40 * k + 0.5 * t)
        e = 20_000.0 + np.cumsum(np.r_[0.0, 200.0 * np.sin(heading[:-1]) * np.diff(t)])
        nn = 25_000.0 + np.cumsum(np.r_[0.0, 200.0 * np.cos(heading[:-1]) * np.diff(t)])
        u = np.full(n, 6000.0)
        rho = np.sqrt(e * e + nn * nn + u * u) + rng.normal(0, SIGMA[0], n)
        az = np.arctan2(e, nn) + rng.normal(0, np.radians(SIGMA[1]), n)
        el = np.arctan2(u, np.hypot(e, nn)) + rng.normal(0, np.radians(SIGMA[2]), n)
        enu, cov_k = converted(rho, az, el, SIGMA[0], np.radians(SIGMA[1]), np.radians(SIGMA[2]))
        seen = rng.random(n) >= 0.1
        seen[0] = True
        z[k, seen], R[k, seen] = enu[seen], cov_k[seen]
        states[k, :, 0], states[k, :, 3], states[k, :, 6] = e, nn, u
        states[k, :, 1], states[k, :, 4] = 200.0 * np.sin(heading), 200.0 * np.cos(heading)
        times[k] = t
    arrays = {"measurements": z.astype(np.float32), "states": states.astype(np.float32), "t": times,
              "dt": np.float64(dt)}
    if cov:
        arrays["meas_cov"] = R.astype(np.float32)
    np.savez(path, **arrays)
    return path, arrays


def _csv(path, arrays):
    """The same detections as CSV rows with their covariances (``r_xx..r_zz``), the float32 values of the .npz."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["track_id", "t", "x", "y", "z", "r_xx", "r_xy", "r_xz", "r_yy", "r_yz", "r_zz"])
        for k, (t, z, c) in enumerate(zip(arrays["t"], arrays["measurements"], arrays["meas_cov"])):
            for ti, zi, ci in zip(t, z.astype(np.float64), c.astype(np.float64)):
                cells = [] if np.isnan(zi).any() else [*zi, *(ci[i, j] for i, j in ((0, 0), (0, 1), (0, 2), (1, 1),
                                                                                    (1, 2), (2, 2)))]
                w.writerow([f"trk{k}", repr(float(ti)), *(repr(float(v)) for v in cells)] + [""] * (9 - len(cells)))
    return path


def test_an_npz_with_meas_cov_is_tracked_by_its_bands_radar_network(tmp_path, capsys):
    src, arrays = _npz(tmp_path / "plots.npz", 5.0, 0.5)
    out = tmp_path / "default.npz"
    assert main(["track", "--input", str(src), "--output", str(out)]) == 0
    err = capsys.readouterr().err
    assert ("note: the .npz carries each detection's covariance and its median scan interval is" in err
            and "tracked by immnet-radar-5s, the shipped network told each plot's covariance" in err)
    assert f"tracked 3 tracks with immnet-radar-5s -> {out}" in err and "the bank" not in err
    got = np.load(out)
    assert sorted(got.files) == ["dt", "mode_probs", "state", "state_cov", "t"]
    assert np.isfinite(got["state"]).all() and got["state_cov"].shape == (3, 30, 9, 9)
    np.testing.assert_array_equal(got["t"], arrays["t"])
    # the shipped weights by name, given meas_cov through the Tracker path: the same estimates
    assert main(["track", "--input", str(src), "--output", str(tmp_path / "w.npz"), "--weights", "radar-5s"]) == 0
    assert "not used" not in capsys.readouterr().err
    by_name = np.load(tmp_path / "w.npz")
    for key in ("state", "mode_probs", "state_cov"):
        np.testing.assert_array_equal(got[key], by_name[key])
    # the same detections as CSV rows with covariances, tracked by the CSV default (float64 rows): the same estimates
    # to float32 rounding of the state (positions ~4e4 m: float32's spacing there is 4e-3 m; measured: < 2e-3 m)
    assert main(["track", "--input", str(_csv(tmp_path / "rows.csv", arrays)), "--output",
                 str(tmp_path / "rows_out.csv")]) == 0
    assert "tracked by immnet-radar-5s" in capsys.readouterr().err
    with open(tmp_path / "rows_out.csv") as f:
        rows = list(csv.DictReader(f))
    csv_state = np.array([[float(r[c]) for c in ("x", "vx", "ax", "y", "vy", "ay", "z", "vz", "az")] for r in rows])
    np.testing.assert_allclose(got["state"].reshape(-1, 9), csv_state, rtol=0, atol=4e-3)
    # immnet evaluate's RMSE of immnet-radar-5s on the .npz is the RMSE of these estimates against the truth
    assert main(["evaluate", "--data", str(src), "--methods", "immnet-radar-5s", "--json",
                 str(tmp_path / "e.json"), "--quiet", "--no-wandb"]) == 0
    pooled = json.loads((tmp_path / "e.json").read_text())["methods"]["immnet-radar-5s"]["rmse_pooled"]
    err3 = got["state"][..., [0, 3, 6]].astype(np.float64) - arrays["states"][..., [0, 3, 6]].astype(np.float64)
    mine = np.sqrt(np.mean(err3.reshape(-1, 3) ** 2, 0))  # every scan scored: a detection at each track's first
    np.testing.assert_allclose([pooled[a] for a in "xyz"], mine, rtol=1e-6)


def test_an_npz_between_the_bands_is_tracked_by_the_nearer_bands_filter(tmp_path, capsys):
    src, _ = _npz(tmp_path / "plots.npz", 8.0)
    assert main(["track", "--input", str(src), "--output", str(tmp_path / "o.npz")]) == 0
    err = capsys.readouterr().err
    assert ("median scan interval is 8 s, whose scans the shipped radar networks (4.5-5.5 s, 10-12 s) were not "
            "trained at: tracked by radar-imm-robust-11s") in err
    assert "(--weights or --checkpoint chooses another tracker)" in err
    got = np.load(tmp_path / "o.npz")
    assert np.isfinite(got["state"]).all() and "state" in got.files and "t" in got.files


def test_an_npz_without_meas_cov_is_the_banks_as_before(tmp_path, capsys):
    src, _ = _npz(tmp_path / "xyz.npz", 5.0, 0.5, cov=False)
    assert main(["track", "--input", str(src), "--output", str(tmp_path / "default.npz")]) == 0
    err = capsys.readouterr().err
    assert "with the bank (" in err and "tracked by" not in err and "'meas_cov'" not in err
    assert main(["track", "--input", str(src), "--output", str(tmp_path / "bank.npz"), "--weights", "bank"]) == 0
    assert (tmp_path / "default.npz").read_bytes() == (tmp_path / "bank.npz").read_bytes()
    # meas_cov beside it changes the default, not --weights bank, which says it does not use it
    src2, _ = _npz(tmp_path / "cov.npz", 5.0, 0.5)
    assert main(["track", "--input", str(src2), "--output", str(tmp_path / "bank2.npz"), "--weights", "bank"]) == 0
    assert ("the bank estimates each track's measurement noise from its measurements: the .npz's 'meas_cov' is not "
            "used") in capsys.readouterr().err
    assert (tmp_path / "bank2.npz").read_bytes() == (tmp_path / "bank.npz").read_bytes()


def test_refusals_on_an_npz_are_one_line(tmp_path, capsys):
    src, _ = _npz(tmp_path / "plots.npz", 5.0, 0.5)
    bare, _ = _npz(tmp_path / "bare.npz", 5.0, 0.5, cov=False)
    out = tmp_path / "o.npz"
    for source, extra, message in (
            (src, ["--adapt"], "immnet track: error: --adapt is the bank's and the shipped networks' option; this .npz "
                               "carries each detection's covariance ('meas_cov') and is tracked by immnet-radar-5s by "
                               "default, which has none: give --weights bank to track it with the bank"),
            (src, ["--guard", "30000,4000"],
             "immnet track: error: --guard is the bank's and the shipped networks' option; this .npz carries each "
             "detection's covariance ('meas_cov') and is tracked by immnet-radar-5s by default, which has none: give "
             "--weights bank to track it with the bank"),
            (src, ["--r", "30"], "immnet track: error: --r and the .npz's 'meas_cov' both give the measurement noise "
                                 "of immnet-radar-5s (the default for an .npz with 'meas_cov'): give one of the two"),
            (bare, ["--weights", "radar-5s"],
             "immnet-radar-5s.ckpt: this network is told each detection's covariance, which "
             f"{bare} does not hold: give the .npz its 'meas_cov' [N, T, 3, 3] (immnet data adsb --sigma-* writes "
             "it), or one std for all with --r METRES")):
        assert main(["track", "--input", str(source), "--output", str(out), *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert err.endswith(message) and "\n" not in err
        assert not out.exists()
