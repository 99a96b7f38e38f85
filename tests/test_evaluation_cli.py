"""``immnet evaluate`` end to end on a small .npz, its errors, and the figures."""

import json

import numpy as np
import pytest

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
