"""Issue 23, item 5: ``immnet track`` writes the state's covariance: the 21 position-velocity entries as CSV
columns after the existing ones, ``state_cov [N, T, 9, 9]`` in an .npz; read back they are the API's."""

import csv
import math

import numpy as np
import pytest
import torch

from immnet import keys
from immnet.cli import main
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.tracking import Tracker
from immnet.data.csvio import COV_COLUMNS, COV_INDEX, OUT_COLUMNS

LEAD = 3  # rows before each track's first detection: no estimate, empty fields


@pytest.fixture(scope="module")
def z():
    """Two tracks of 24 scans, missed detections inside, none in their first ``LEAD`` rows."""
    z = generate(2, seed=12, spec=DataSpec(T=24, min_segment=8))[keys.MEASUREMENTS].double().numpy().copy()
    z[:, :LEAD] = np.nan
    z[0, [10, 11, 18]] = np.nan
    z[1, 20] = np.nan
    return z


def _write(path, z, times=None):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["track_id", "t", "x", "y", "z"])
        for k in range(z.shape[1]):  # the tracks' rows interleaved
            for i, tid in enumerate(("a", "b")):
                t = k if times is None else times[i][k]
                w.writerow([tid, repr(float(t)), *(("", "", "") if np.isnan(z[i, k]).any() else (repr(float(v)) for v in z[i, k]))])


def _read(path):
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        rows = list(reader)
    assert tuple(reader.fieldnames) == OUT_COLUMNS
    by_track = {tid: [r for r in rows if r["track_id"] == tid] for tid in ("a", "b")}
    return {tid: np.array([[math.nan if r[c] == "" else float(r[c]) for c in COV_COLUMNS] for r in rs])
            for tid, rs in by_track.items()}


def _columns(cov: np.ndarray) -> np.ndarray:
    return np.stack([cov[..., i, j] for i, j in COV_INDEX], -1)


def test_the_columns_are_the_old_ones_then_the_position_velocity_covariance():
    assert OUT_COLUMNS[:15] == ("track_id", "t", "x", "vx", "ax", "y", "vy", "ay", "z", "vz", "az",
                                "p_cv", "p_ca", "p_ctp", "p_ctm")
    assert OUT_COLUMNS[15:] == COV_COLUMNS and len(COV_COLUMNS) == 21
    named = dict(zip(COV_COLUMNS, COV_INDEX))
    assert named["cov_xx"] == (0, 0) and named["cov_yz"] == (3, 6) and named["cov_vxvz"] == (1, 7)
    assert named["cov_zvx"] == (6, 1) and named["cov_vzvz"] == (7, 7)
    pairs = {tuple(sorted(ij)) for ij in COV_INDEX}  # the 6x6 position-velocity block's entries, each once
    assert pairs == {(i, j) for i in (0, 1, 3, 4, 6, 7) for j in (0, 1, 3, 4, 6, 7) if i <= j}


def test_csv_covariance_columns_read_back_as_the_trackers(tmp_path, z):
    _write(tmp_path / "in.csv", z)
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(tmp_path / "out.csv")]) == 0
    got = _read(tmp_path / "out.csv")
    api = Tracker.pretrained().track(torch.from_numpy(z), return_cov=True)[keys.STATE_COV]  # the CSV's float64
    want = _columns(api.double().numpy())
    for i, tid in enumerate(("a", "b")):
        assert np.isnan(got[tid][:LEAD]).all() and np.isfinite(got[tid][LEAD:]).all()
        # the bank's mixture is float64, written to the CSV's nine significant digits
        np.testing.assert_allclose(got[tid][LEAD:], want[i][LEAD:], rtol=1e-8, atol=0)


def test_csv_covariance_of_a_method_any_interval(tmp_path, z, capsys):
    from immnet.filters.methods import build_method
    from immnet.data.csvio import read_tracks_csv
    from immnet.tracking.segments import split_rows, track_rows

    times = [np.cumsum(np.r_[0.0, np.full(z.shape[1] - 1, 2.5)]) + 1_733_070_000.25, np.arange(z.shape[1]) * 4.0]
    _write(tmp_path / "in.csv", z, times)
    args = ["track", "--input", str(tmp_path / "in.csv"), "--method"]
    assert main(args + ["imm-ekf", "--output", str(tmp_path / "ekf.csv")]) == 0
    got = _read(tmp_path / "ekf.csv")
    rows = read_tracks_csv(tmp_path / "in.csv")
    segs, offset = split_rows(rows.ids, rows.t, rows.z)
    _, _, cov = track_rows(build_method("imm-ekf", return_cov=True), segs, offset, return_cov=True)
    for tid in ("a", "b"):
        mine = [r for r in range(len(rows)) if rows.ids[r] == tid]
        np.testing.assert_allclose(got[tid], _columns(cov[mine]), rtol=1e-8, atol=0)
        assert np.isnan(got[tid][:LEAD]).all() and np.isfinite(got[tid][LEAD:]).all()
    capsys.readouterr()
    assert main(args + ["measurements", "--output", str(tmp_path / "raw.csv")]) == 0
    assert all(np.isnan(v).all() for v in _read(tmp_path / "raw.csv").values())
    assert "no covariance: measurements keeps no covariance" in capsys.readouterr().err


def test_npz_state_cov_is_the_trackers(tmp_path, z):
    np.savez(tmp_path / "in.npz", measurements=z, dt=1.0)
    assert main(["track", "--input", str(tmp_path / "in.npz"), "--output", str(tmp_path / "out.npz")]) == 0
    out = np.load(tmp_path / "out.npz")
    api = Tracker.pretrained().track(torch.from_numpy(z).float(), return_cov=True)
    assert out["state_cov"].shape == (2, z.shape[1], 9, 9)
    np.testing.assert_array_equal(out["state_cov"], api[keys.STATE_COV].numpy())
    assert np.isnan(out["state_cov"][:, :LEAD]).all() and np.isfinite(out["state_cov"][:, LEAD:]).all()
