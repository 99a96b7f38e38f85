"""``immnet evaluate`` end to end on a small .npz, its errors, and the figures."""

import json
import sys
import types

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from immnet import keys
import immnet.cli
from immnet.cli import main

generate = pytest.importorskip("immnet.data.generate").generate
DataSpec = pytest.importorskip("immnet.data.spec").DataSpec


@pytest.fixture(autouse=True)
def only_our_commands(monkeypatch):
    """The evaluation commands alone (other packages' command modules may still be in progress)."""
    monkeypatch.setattr(immnet.cli, "_COMMAND_MODULES", ("immnet.evaluation.cli",))


@pytest.fixture(scope="module")
def npz(tmp_path_factory):
    td = generate(6, seed=11, spec=DataSpec(T=90, min_segment=25))
    d = tmp_path_factory.mktemp("data")
    full, meas_only = d / "full.npz", d / "meas.npz"
    arrays = {k: td[k].numpy() for k in (keys.STATES, keys.MEASUREMENTS, keys.MODE, keys.TURN_RATE, keys.R)}
    np.savez(full, dt=1.0, **arrays)
    np.savez(meas_only, dt=1.0, measurements=arrays[keys.MEASUREMENTS])
    no_mode = d / "no_mode.npz"
    np.savez(no_mode, dt=1.0, states=arrays[keys.STATES], measurements=arrays[keys.MEASUREMENTS])
    return full, meas_only, no_mode


def test_evaluate_writes_table_json_and_figures(npz, tmp_path, capsys):
    out, figs = tmp_path / "r.json", tmp_path / "figs"
    rc = main(["evaluate", "--data", str(npz[0]), "--methods", "measurements,imm-accurate,clairvoyant",
               "--json", str(out), "--figures", str(figs), "--seed", "3", "--quiet"])
    assert rc == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].split()[:2] == ["method", "x"] and [r.split()[0] for r in table[2:]] == [
        "measurements", "imm-accurate", "clairvoyant"]
    doc = json.loads(out.read_text())
    assert doc["n_trajectories"] == 6 and doc["data"] == str(npz[0]) and doc["split"] == "all" and doc["seed"] == 3
    assert list(doc["methods"]) == ["measurements", "imm-accurate", "clairvoyant"]
    for name, row in doc["methods"].items():
        for k in ("rmse", "rmse_pooled", "rmse_post_switch"):
            assert set(row[k]) == {"x", "y", "z", "avg"} and all(np.isfinite(list(row[k].values())))
        assert row["seconds"] >= 0
    assert "mode_accuracy" in doc["methods"]["imm-accurate"] and "mode_accuracy" not in doc["methods"]["measurements"]
    assert np.array(doc["methods"]["imm-accurate"]["confusion"]).sum() == 6 * 90
    pngs = sorted(p.name for p in figs.glob("*.png"))
    assert "rmse_over_time.png" in pngs and "confusion_imm-accurate.png" in pngs
    assert sum(p.endswith("_track.png") for p in pngs) == 2 and sum(p.endswith("_modes.png") for p in pngs) == 2
    assert all((figs / p).stat().st_size > 10_000 and (figs / p).read_bytes()[:4] == b"\x89PNG" for p in pngs)


def test_default_methods_skip_the_clairvoyant_without_ground_truth(npz, capsys):
    assert main(["evaluate", "--data", str(npz[2]), "--quiet", "--limit", "2"]) == 0
    cap = capsys.readouterr()
    assert "skipping clairvoyant" in cap.err and "mode" in cap.err
    rows = [r.split()[0] for r in cap.out.splitlines()[2:]]
    assert "clairvoyant" not in rows and rows[0] == "measurements"
    assert all(r.split()[5] == "-" for r in cap.out.splitlines()[2:])  # no labels: no post-switch RMSE


@pytest.mark.parametrize(
    "args, message",
    [
        (["--methods", "measurements,nope"], "unknown method 'nope'.*available: measurements"),
        (["--methods", "clairvoyant"], "method 'clairvoyant' needs .*mode, turn_rate, r, which the data lacks"),
        (["--methods", "measurements"], "ground-truth 'states'"),
    ],
    ids=["unknown-method", "clairvoyant-without-truth", "no-states"],
)
def test_evaluate_errors(npz, capsys, args, message):
    assert main(["evaluate", "--data", str(npz[1]), "--quiet", *args]) == 2
    import re

    assert re.search(message, capsys.readouterr().err)


def test_missing_data_file(tmp_path, capsys):
    assert main(["evaluate", "--data", str(tmp_path / "none.npz")]) == 2
    assert "not found" in capsys.readouterr().err


def test_tune_refuses_a_file(npz, capsys):
    assert main(["tune-imm", "--data", str(npz[0])]) == 2
    assert "validation split" in capsys.readouterr().err


# --- bad input at the edge, gated measurements, what is scored, strict JSON ----------------------
def _save(path, arrays, **over):
    a = dict(arrays, **over)
    np.savez(path, **{k: v for k, v in a.items() if v is not None})
    return path


@pytest.fixture(scope="module")
def arrays(npz):
    with np.load(npz[0]) as z:
        return {k: z[k] for k in z.files}


def _truncated(path, arrays):
    _save(path, arrays)
    path.write_bytes(path.read_bytes()[:4000])


BAD = {
    "dt-zero": lambda p, a: _save(p, a, dt=np.float64(0.0)),
    "dt-nan": lambda p, a: _save(p, a, dt=np.float64(np.nan)),
    "dt-empty": lambda p, a: _save(p, a, dt=np.array([])),
    "T-zero": lambda p, a: _save(p, a, **{k: a[k][:, :0] for k in ("states", "measurements", "mode", "turn_rate")}),
    "mode-7": lambda p, a: _save(p, a, mode=np.where(np.arange(90) == 40, 7, a["mode"])),
    "states-float16": lambda p, a: _save(p, a, states=a["states"].astype(np.float16)),
    "truncated": _truncated,
    "empty-file": lambda p, a: p.write_bytes(b""),
}


@pytest.mark.parametrize("make", list(BAD.values()), ids=list(BAD))
def test_bad_npz_ends_with_exit_2_and_one_line(arrays, tmp_path, capsys, make):
    """Issue 20, item 2: `immnet evaluate --data BAD.npz` exits 2 with one line naming what is wrong
    (no traceback, no table scored on it)."""
    path = tmp_path / "bad.npz"
    make(path, arrays)
    assert main(["evaluate", "--data", str(path), "--methods", "measurements,imm-tuned", "--quiet"]) == 2
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("immnet evaluate: error: ") and str(path) in lines[0]
    assert cap.out == ""


from immnet.filters.methods import configured_methods  # noqa: E402

METHODS = configured_methods()  # every method of configs/methods/, the model-based ones and the learned


def _td(arrays, **over):
    a = dict(arrays, **over)
    n = a["measurements"].shape[0]
    data = {k: torch.from_numpy(np.asarray(a[k])) for k in ("states", "measurements", "mode", "turn_rate", "r")}
    data["dt"] = torch.full((n,), float(a["dt"]), dtype=torch.float64)
    return TensorDict(data, batch_size=[n])


@pytest.mark.parametrize("name", METHODS)
def test_unreportable_measurements_are_gated_missed_detections(arrays, name):
    """Issue 20, item 2: one `inf` and one 1e30 measurement become counted missed detections before
    any method sees them: no crash (imm-ekf raised LinAlgError), no NaN, and the very numbers of the
    method run on data whose two scans were missed detections from the start."""
    from immnet.evaluation import build_method, evaluate
    from tiny_runs import at_an_interval_it_takes

    z = arrays["measurements"].copy()
    z[0, 30] = [np.inf, 0.0, 0.0]
    z[4, 50, 2] = 1e30
    clean = z.copy()
    clean[0, 30] = clean[4, 50] = np.nan
    method = build_method(name)
    got = evaluate({name: method}, at_an_interval_it_takes(method, _td(arrays, measurements=z)), progress=False)[name]
    want = evaluate({name: method}, at_an_interval_it_takes(method, _td(arrays, measurements=clean)), progress=False)[name]
    for k in ("rmse", "rmse_pooled", "rmse_post_switch"):
        assert got[k] is not None and np.isfinite(list(got[k].values())).all()
        assert got[k] == want[k]
    assert torch.equal(got["per_trajectory"], want["per_trajectory"])
    assert got["gated"] == 2 and want["gated"] == 0
    assert got["counts"]["nan_scans"] == 0 and got["counts"]["diverged"] == 0


def test_gating_is_reported_and_its_limit_configurable(arrays, tmp_path, capsys):
    """Issue 20, item 2: the gated measurements are reported on stderr and in the JSON;
    `--max-position` sets the limit (a 5e6 m measurement passes the default 1e7, not 1e6)."""
    z = arrays["measurements"].copy()
    z[0, 30] = [np.inf, 0.0, 0.0]
    z[4, 50, 2] = 1e30
    z[2, 10, 0] = 5e6
    path = _save(tmp_path / "z.npz", arrays, measurements=z)
    for limit, n in ((None, 2), ("1e6", 3)):
        out = tmp_path / "r.json"
        extra = [] if limit is None else ["--max-position", limit]
        args = ["evaluate", "--data", str(path), "--methods", "imm-ekf", "--quiet", "--json", str(out), *extra]
        assert main(args) == 0
        err = capsys.readouterr().err
        assert f"note: {n} measurements beyond what a sensor reports" in err and "missed detections" in err
        doc = json.loads(out.read_text())
        assert doc["scans"]["gated"] == n and np.isfinite(doc["methods"]["imm-ekf"]["rmse"]["avg"])
    assert main(["evaluate", "--data", str(path), "--methods", "imm-ekf", "--max-position", "0"]) == 2
    assert "must be a positive number" in capsys.readouterr().err


class Diverging:
    """The truth as its estimate, except NaN from step 60 on in trajectory 2 (a tracker that fails)."""

    needs = ("states",)
    name = "diverging"

    def track(self, batch):
        state = batch["states"].clone()
        if batch.batch_size[0] > 2:
            state[2, 60:] = float("nan")
        return TensorDict({"state": state}, batch_size=batch.batch_size)


def _strict(text):
    def refuse(c):
        raise ValueError(f"not JSON: {c}")

    return json.loads(text, parse_constant=refuse)


def test_json_is_strict_with_padded_truth_and_a_diverged_method(arrays, tmp_path, capsys, monkeypatch):
    """Issue 20, item 3: with truth NaN-padded after a track's end (mode -1 there) and a method
    whose estimate turns NaN, `--json` is valid JSON (no NaN: null) and says what was scored; the
    padded set's numbers equal a float64 computation over the scans with truth."""
    mod = types.ModuleType("fake_diverging")
    mod.Diverging = Diverging
    monkeypatch.setitem(sys.modules, "fake_diverging", mod)
    (tmp_path / "diverging.yaml").write_text("class_path: fake_diverging.Diverging\n")
    monkeypatch.setattr("immnet.filters.registry.METHODS_DIR", tmp_path)
    s, z, m = arrays["states"].copy(), arrays["measurements"].copy(), arrays["mode"].copy()
    s[1, 70:], z[1, 70:], m[1, 70:] = np.nan, np.nan, -1
    s[5], m[5] = np.nan, -1
    path = _save(tmp_path / "p.npz", arrays, states=s, measurements=z, mode=m)
    out = tmp_path / "r.json"
    assert main(["evaluate", "--data", str(path), "--methods", "measurements,diverging", "--quiet",
                 "--json", str(out)]) == 0
    cap = capsys.readouterr()
    doc = _strict(out.read_text())
    assert doc["scans"] == {"gated": 0, "scans": 540, "scored": 540 - 20 - 90, "without_truth": 110,
                            "before_first_detection": 0, "trajectories": 6, "excluded": 1}
    d = doc["methods"]["diverging"]
    assert d["rmse"] is None and d["rmse_pooled"] is None and d["nan_scans"] == 30 and d["diverged"] == 1
    assert "diverged (1 tracks)" in cap.out and "diverging: the estimate is not finite at 30 scored scans" in cap.err
    # the raw measurements' RMSE equals a float64 computation over the scored scans only (the
    # loader stores float32): the last detection held, per trajectory over its scans with truth
    s32, z32 = s.astype(np.float32).astype(np.float64), z.astype(np.float32).astype(np.float64)
    rows = []
    for i in range(5):
        held, sq = None, []
        for t in range(90):
            if not np.isnan(z32[i, t]).any():
                held = z32[i, t]
            if not np.isnan(s32[i, t]).any():
                sq.append((held - s32[i, t, [0, 3, 6]]) ** 2)
        rows.append(np.sqrt(np.mean(sq, axis=0)))
    assert [doc["methods"]["measurements"]["rmse"][a] for a in "xyz"] == pytest.approx(np.mean(rows, 0), rel=1e-12)


def test_default_split_of_a_directory_is_its_test_split(tmp_path, capsys):
    """Issue 20, item 2: ``immnet evaluate --data DIR`` (default ``--split test``) used to end in a
    TypeError traceback (the loaded TensorDict was handed to the DataModule as a path). It scores the
    DataModule's test split: checked against a float64 numpy RMSE of the raw measurements on it."""
    from immnet.data.datamodule import LASTDataModule
    from immnet.data.storage import write_dataset

    d = write_dataset(tmp_path / "set", n=40, seed=3, spec=DataSpec(T=60, min_segment=20))
    out = tmp_path / "r.json"
    assert main(["evaluate", "--data", str(d), "--methods", "measurements", "--quiet", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    test = LASTDataModule(d).split("test")
    assert doc["split"] == "test" and doc["n_trajectories"] == test.batch_size[0] == 4
    err = test[keys.MEASUREMENTS].double().numpy() - test[keys.STATES][..., [0, 3, 6]].double().numpy()
    want = np.sqrt((err ** 2).mean(axis=1)).mean(axis=0).mean()
    assert doc["methods"]["measurements"]["rmse"]["avg"] == pytest.approx(want, rel=1e-6)
