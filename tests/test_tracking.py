"""``immnet track``: CSV and .npz in and out, against the Python API; malformed CSV names its line."""

import csv
import math

import numpy as np
import pytest
import torch

from immnet.cli import main
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.tracking import Tracker
from immnet.training import Stage2Module


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """An untrained (but complete) IMMNet checkpoint, as Lightning writes it."""
    import lightning as L

    torch.manual_seed(0)
    module = Stage2Module(net={"model_set": "configs/model_sets/imm4.yaml"})
    trainer = L.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False, max_epochs=0)
    trainer.strategy.connect(module)
    path = tmp_path_factory.mktemp("ckpt") / "net.ckpt"
    trainer.save_checkpoint(path)
    return path


@pytest.fixture(scope="module")
def scans():
    td = generate(3, seed=8, spec=DataSpec(T=45, min_segment=15))
    return td["measurements"].float().numpy()


def _write_csv(path, rows):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["track_id", "t", "x", "y", "z"])
        w.writerows(rows)


def test_csv_with_interleaved_tracks_and_gaps_matches_python_api(tmp_path, checkpoint, scans):
    # track "a" starts at t=100, "b" at t=103 with a skipped scan and an empty row, "c" at 100.5 (dt apart)
    rows, expected_z = [], np.full((3, 45, 3), np.nan, dtype=np.float32)
    starts = {"a": 100.0, "b": 103.0, "c": 100.5}
    for k in range(45):
        for i, tid in enumerate("abc"):
            if tid == "b" and k == 7:
                continue  # a missed scan (time gap)
            z = scans[i, k]
            if tid == "b" and k == 12:
                rows.append([tid, starts[tid] + k, "", "", ""])  # a missed detection
                continue
            rows.append([tid, starts[tid] + k, *map(float, z)])
            expected_z[i, k] = z
    _write_csv(tmp_path / "in.csv", rows)
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(tmp_path / "out.csv"), "--checkpoint", str(checkpoint)]) == 0
    with open(tmp_path / "out.csv") as f:
        out = list(csv.DictReader(f))
    assert len(out) == len(rows)
    api = Tracker.from_checkpoint(checkpoint).track(torch.from_numpy(expected_z))
    for row in out:
        i = "abc".index(row["track_id"])
        k = round(float(row["t"]) - starts[row["track_id"]])
        est = [float(row[c]) for c in ("x", "vx", "ax", "y", "vy", "ay", "z", "vz", "az")]
        np.testing.assert_allclose(est, api["state"][i, k].numpy(), rtol=1e-5, atol=1e-4)
        probs = [float(row[c]) for c in ("p_cv", "p_ca", "p_ctp", "p_ctm")]
        assert math.isclose(sum(probs), 1.0, abs_tol=1e-4)


def test_npz_in_and_out(tmp_path, checkpoint, scans):
    np.savez(tmp_path / "in.npz", measurements=scans, dt=1.0)
    assert main(["track", "--input", str(tmp_path / "in.npz"), "--output", str(tmp_path / "out.npz"), "--checkpoint", str(checkpoint)]) == 0
    out = np.load(tmp_path / "out.npz")
    assert out["state"].shape == (3, 45, 9) and out["mode_probs"].shape == (3, 45, 4)


@pytest.mark.parametrize(
    "rows,message",
    [
        ([["a", 0, 1, 2, 3], ["a", 1, "x1", 2, 3]], "line 3: column 'x' is not a number"),
        ([["a", 0, 1, 2, 3], ["a", 0, 1, 2, 3]], "line 3: time 0 of track 'a' is not after"),
        ([["a", 1, 1, 2, 3], ["b", 0, 1, 2, 3], ["a", 0.5, 1, 2, 3]], "line 4: time 0.5 of track 'a'"),
        ([["a", 0, 1, 2, 3], ["a", 1.5, 1, 2, 3]], "line 3: time 1.5 of track 'a' is not a whole number"),
        ([["a", "", 1, 2, 3]], "line 2: column 't' is empty"),
    ],
    ids=["non-numeric", "repeated-time", "unsorted-time", "off-grid-time", "empty-time"],
)
def test_malformed_csv_names_the_line(tmp_path, checkpoint, rows, message, capsys):
    _write_csv(tmp_path / "bad.csv", rows)
    assert main(["track", "--input", str(tmp_path / "bad.csv"), "--output", str(tmp_path / "o.csv"), "--checkpoint", str(checkpoint)]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o.csv").exists()


def test_missing_column_is_named(tmp_path, checkpoint, capsys):
    (tmp_path / "bad.csv").write_text("track_id,t,x,y\na,0,1,2\n")
    assert main(["track", "--input", str(tmp_path / "bad.csv"), "--output", str(tmp_path / "o.csv"), "--checkpoint", str(checkpoint)]) == 2
    assert "line 1: missing column(s) z" in capsys.readouterr().err


def test_checkpoint_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        Tracker.from_checkpoint(tmp_path / "nope.ckpt")
    (tmp_path / "junk.ckpt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        Tracker.from_checkpoint(tmp_path / "junk.ckpt")


def test_track_guard_option_matches_the_python_api(tmp_path, capsys):
    """``--guard none`` / ``OUTER,INNER`` load the shipped 3D-LAST weights with no range guard / another region,
    as ``Tracker.pretrained(guard=...)`` does; the region changes the tracks that fly beyond it."""
    from immnet.tracking.tracker import PRETRAINED

    z = generate(4, seed=31, spec=DataSpec(T=60, min_segment=20))["measurements"].float().numpy()
    np.savez(tmp_path / "in.npz", measurements=z, dt=1.0)
    outs = {}
    for text, guard in (("none", None), ("15000,4000", {"outer": 15_000.0, "inner": 4_000.0})):
        assert main(["track", "--input", str(tmp_path / "in.npz"), "--output", str(tmp_path / "out.npz"), "--weights", "3dlast",
                     "--guard", text]) == 0
        outs[text] = np.load(tmp_path / "out.npz")["state"]
        api = Tracker.from_checkpoint(PRETRAINED, guard=guard).track(torch.from_numpy(z))
        np.testing.assert_allclose(outs[text], api["state"].numpy(), rtol=1e-5, atol=1e-4)
    rho = np.hypot(z[..., 0], z[..., 1])
    assert (rho > 15_000).any(), "no track flies beyond the region: the comparison below would be empty"
    assert np.abs(outs["none"] - outs["15000,4000"]).max() > 0.1
    capsys.readouterr()
    assert main(["track", "--input", str(tmp_path / "in.npz"), "--output", str(tmp_path / "out.npz"), "--guard", "far"]) == 2
    assert "--guard must be 'checkpoint', 'none' or 'OUTER,INNER'" in capsys.readouterr().err


def test_a_guard_needs_filter_experts(checkpoint):
    with pytest.raises(ValueError, match="range guard needs filter experts"):
        Tracker.from_checkpoint(checkpoint, guard=None)
