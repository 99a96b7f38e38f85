"""``immnet evaluate`` with the shipped weights on an ``.npz`` the project did not generate.

The data come from a little simulator written here with numpy (not ``immnet.data.generate``):
straight flight, then a constant-rate horizontal turn to the end, T = 150, float64, missed
detections as NaN, ``states`` given but no ``mode``, ``turn_rate`` or ``r``.
"""

import json
import re

import numpy as np
import pytest

import immnet.cli
from immnet.tracking.tracker import PRETRAINED


def simulate(n: int, T: int, dt: float, seed: int = 0, p_miss: float = 0.03):
    """``(states [n,T,9], measurements [n,T,3])``: CV until a random step, then a coordinated turn."""
    rng = np.random.default_rng(seed)
    rho, az = rng.uniform(10e3, 25e3, n), rng.uniform(0, 2 * np.pi, n)
    spd, hdg = rng.uniform(120, 250, n), rng.uniform(0, 2 * np.pi, n)
    pos = np.stack([rho * np.cos(az), rho * np.sin(az), rng.uniform(3e3, 8e3, n)], 1)
    vel = np.stack([spd * np.cos(hdg), spd * np.sin(hdg), rng.uniform(-3, 3, n)], 1)
    t_turn = rng.integers(int(0.3 * T), int(0.6 * T), n)
    w = np.deg2rad(rng.uniform(2, 6, n)) * rng.choice([-1, 1], n)
    states = np.zeros((n, T, 9))
    for t in range(T):
        turning = t > t_turn
        if t > 0:  # exact motion over one interval: the velocity rotates by w dt while turning
            wdt = np.where(turning, w * dt, 0.0)
            c, s = np.cos(wdt), np.sin(wdt)
            ws = np.where(turning, w, 1.0)
            s_w, c_w = np.where(turning, s / ws, dt), np.where(turning, (1 - c) / ws, 0.0)
            vx, vy = vel[:, 0].copy(), vel[:, 1].copy()
            pos += np.stack([s_w * vx - c_w * vy, c_w * vx + s_w * vy, dt * vel[:, 2]], 1)
            vel[:, 0], vel[:, 1] = c * vx - s * vy, s * vx + c * vy
        acc = np.where(turning[:, None], np.stack([-w * vel[:, 1], w * vel[:, 0], 0 * w], 1), 0.0)
        states[:, t, 0::3], states[:, t, 1::3], states[:, t, 2::3] = pos, vel, acc
    r = rng.uniform(2, 6, n)
    z = states[:, :, 0::3] + r[:, None, None] * rng.standard_normal((n, T, 3))
    miss = rng.random((n, T)) < p_miss
    miss[:, 0] = False  # every track detected at its first scan (before it, no tracker has an estimate)
    miss[0, 1:3] = True  # one track misses its second and third scans: the start spans the gap
    z[miss] = np.nan
    return states, z


def raw_measurement_rmse(states, z):
    """docs/spec.md section 5's table RMSE of ``x_hat_t = z_t``, a miss holding the last detection: ``{x, y, z, avg}``."""
    filled = z.copy()
    for t in range(1, z.shape[1]):
        gap = np.isnan(filled[:, t]).any(-1)
        filled[gap, t] = filled[gap, t - 1]
    err = filled - states[:, :, 0::3]
    per_axis = np.sqrt((err**2).mean(axis=1)).mean(axis=0)
    return {"x": per_axis[0], "y": per_axis[1], "z": per_axis[2], "avg": per_axis.mean()}


@pytest.fixture(autouse=True)
def commands(monkeypatch):
    monkeypatch.setattr(immnet.cli, "_COMMAND_MODULES", ("immnet.evaluation.cli", "immnet.tracking.cli"))


@pytest.fixture(scope="module")
def foreign(tmp_path_factory):
    states, z = simulate(n=30, T=150, dt=1.0)
    path = tmp_path_factory.mktemp("foreign") / "tracks.npz"
    np.savez(path, measurements=z, states=states, dt=np.float64(1.0))
    return path, states, z


def test_shipped_weights_on_foreign_npz(foreign, tmp_path, capsys):
    path, states, z = foreign
    assert np.isnan(z).any() and z.dtype == np.float64
    out = tmp_path / "r.json"
    rc = immnet.cli.main(["evaluate", "--data", str(path), "--methods", "measurements,imm-tuned,immnet",
                          "--checkpoint", f"immnet={PRETRAINED}", "--json", str(out), "--quiet"])
    assert rc == 0, capsys.readouterr().err
    doc = json.loads(out.read_text())
    assert doc["n_trajectories"] == 30 and doc["split"] == "all"
    rows = doc["methods"]
    assert list(rows) == ["measurements", "imm-tuned", "immnet"]
    for name, row in rows.items():
        for k in ("rmse", "rmse_pooled"):
            assert set(row[k]) == {"x", "y", "z", "avg"} and np.isfinite(list(row[k].values())).all(), (name, k)
        assert row["rmse_post_switch"] is None and "mode_accuracy" not in row  # no labels in the file
    # independent: numpy from the file itself (stored as float32 on loading, hence the tolerance)
    want = raw_measurement_rmse(states, z)
    for axis, value in want.items():
        assert rows["measurements"]["rmse"][axis] == pytest.approx(value, rel=1e-4), axis
    # a working tracker beats the raw measurements (here about 2.5 m against 17 m, the held detections
    # over misses dominating), and even their noise alone at the detected steps (about 4 m)
    assert rows["immnet"]["rmse"]["avg"] < rows["measurements"]["rmse"]["avg"]
    noise = z - states[:, :, 0::3]
    noise_rmse = np.nanmean(np.sqrt(np.nanmean(noise**2, axis=1)), axis=0).mean()
    assert rows["immnet"]["rmse"]["avg"] < noise_rmse


def test_clairvoyant_names_the_missing_arrays(foreign, capsys):
    rc = immnet.cli.main(["evaluate", "--data", str(foreign[0]), "--methods", "clairvoyant", "--quiet"])
    assert rc == 2
    err = capsys.readouterr().err
    assert re.search(r"'clairvoyant' needs mode, turn_rate, r, which the data lacks", err), err


def test_learned_trackers_refuse_another_dt(tmp_path, capsys):
    """Trained at dt = 1 s, IMMNet on dt = 0.5 s data would report half the true velocities: an error."""
    states, z = simulate(n=4, T=60, dt=0.5, seed=1)
    path = tmp_path / "half.npz"
    np.savez(path, measurements=z, states=states, dt=np.float64(0.5))
    rc = immnet.cli.main(["evaluate", "--data", str(path), "--methods", "measurements,immnet", "--quiet"])
    assert rc == 2
    assert re.search(r"immnet was trained on data sampled at dt = 1 s but this data has dt = 0.5 s",
                     capsys.readouterr().err)
    # by default the learned methods are skipped with a note, the model-based ones still run
    rc = immnet.cli.main(["evaluate", "--data", str(path), "--methods", "measurements,imm-accurate", "--quiet"])
    assert rc == 0
    rc = immnet.cli.main(["evaluate", "--data", str(path), "--quiet", "--json", str(tmp_path / "r.json")])
    cap = capsys.readouterr()
    assert rc == 0 and "skipping immnet: immnet was trained on data sampled at dt = 1 s" in cap.err
    methods = json.loads((tmp_path / "r.json").read_text())["methods"]
    assert "immnet" not in methods and "kalmannet" not in methods and "imm-tuned" in methods
    # the online tracker's .npz path says the same
    rc = immnet.cli.main(["track", "--input", str(path), "--output", str(tmp_path / "o.npz"), "--weights", "3dlast"])
    assert rc == 2 and "dt = 0.5 s" in capsys.readouterr().err and not (tmp_path / "o.npz").exists()
