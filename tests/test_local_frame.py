"""Each track is tracked in its own frame (``immnet.tracking.networks.frame_origin``: its first detection, in float64),
so that coordinates far from the radar keep float32's digits: a shift of the input shifts the output exactly, through
``Tracker`` and ``NetworkBank``, ``track`` and ``step``, and ``immnet track``'s CSV paths (issue 60 item 5)."""

import csv
import math

import numpy as np
import pytest
import torch

from immnet import keys
from immnet.cli import main
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.tracking.bank import NetworkBank
from immnet.tracking.networks import frame_origin
from immnet.tracking.tracker import Tracker

SHIFT = torch.tensor([9.9e6, -9.9e6, 5e6], dtype=torch.float64)  # within max_position (1e7 m) per component
POS, MOTION = [0, 3, 6], [1, 2, 4, 5, 7, 8]  # the state is [x, vx, ax, y, vy, ay, z, vz, az]


@pytest.fixture(scope="module")
def z():
    z = generate(3, seed=5, spec=DataSpec(T=30, min_segment=10))[keys.MEASUREMENTS].double()
    z[1, :3] = float("nan")  # a track that starts late: its frame is its first detection, not scan 0's row
    z[2, 12:15] = float("nan")
    return z


def _shifted_as(got, ref, shift):
    """``got`` (states ``[..., 9]`` of the shifted input) is ``ref`` (of the input) plus ``shift`` in position: to 1 mm,
    velocities and accelerations to 1e-4 relative; NaN where NaN."""
    want = ref.double().clone()
    want[..., POS] += shift
    torch.testing.assert_close(got[..., POS].double(), want[..., POS], rtol=0, atol=1e-3, equal_nan=True)
    torch.testing.assert_close(got[..., MOTION].double(), want[..., MOTION], rtol=1e-4, atol=1e-6, equal_nan=True)
    assert got.dtype == torch.float64  # positions in float64: a float32 of 1e7 m is a metre wide


def _trackers():
    return {"general": Tracker.pretrained("general"), "bank": NetworkBank.from_names()}


@pytest.fixture(scope="module")
def trackers():
    return _trackers()


@pytest.mark.parametrize("which", ["general", "bank"])
def test_a_shifted_track_is_tracked_shifted_by_track(which, trackers, z):
    tracker = trackers[which]
    iv = torch.ones(z.shape[:2], dtype=torch.float64)
    ref = tracker.track(z, intervals=iv, return_cov=True)
    got = tracker.track(z + SHIFT, intervals=iv, return_cov=True)
    assert float(got[keys.STATE][0, 0, 0]) > 9e6  # really there, not gated
    _shifted_as(got[keys.STATE], ref[keys.STATE], SHIFT)
    torch.testing.assert_close(got[keys.STATE_COV], ref[keys.STATE_COV], rtol=1e-6, atol=1e-6, equal_nan=True)
    if which == "general":  # each expert's posterior too, [B, T, M, 9]
        _shifted_as(got[keys.ROLLOUT_EXPERT_POST], ref[keys.ROLLOUT_EXPERT_POST], SHIFT)
    else:
        torch.testing.assert_close(got[keys.MEMBER_PROBS], ref[keys.MEMBER_PROBS], rtol=1e-6, atol=1e-7, equal_nan=True)


@pytest.mark.parametrize("which", ["general", "bank"])
def test_a_shifted_track_is_tracked_shifted_by_step(which, trackers, z):
    """``step`` as ``track``, a reset in mid-sequence included (the track's frame moves to its next detection)."""
    tracker = trackers[which]
    outs = {}
    for name, zz in (("ref", z), ("got", z + SHIFT)):
        tracker.reset(3)
        outs[name] = [tracker.step(zz[:, t], dt=1.0, reset=torch.tensor([False, t == 20, False])) for t in range(30)]
    for key in (keys.FUSED, keys.EXPERT_POST) if which == "general" else (keys.FUSED,):
        _shifted_as(torch.stack([o[key] for o in outs["got"]], 1), torch.stack([o[key] for o in outs["ref"]], 1),
                    SHIFT)
    torch.testing.assert_close(torch.stack([o[keys.FUSED_COV] for o in outs["got"]], 1),
                               torch.stack([o[keys.FUSED_COV] for o in outs["ref"]], 1), rtol=1e-6, atol=1e-6,
                               equal_nan=True)
    assert outs["got"][20][keys.FUSED][1, [1, 4, 7]].eq(0).all()  # restarted there: a first detection, no velocity


def test_a_track_s_frame_is_its_first_detection_and_a_guarded_network_keeps_the_radar_s(z):
    """The origin is each track's first detection (track 1's at scan 3); a network with a range guard (3D-LAST's)
    keeps the radar's frame, whose positions its guard's rules read: its output is its rollout's on the radar-centred
    positions."""
    general = Tracker.pretrained("general")
    torch.testing.assert_close(frame_origin(general.net, z), torch.stack([z[0, 0], z[1, 3], z[2, 0]]), rtol=0, atol=0)
    guarded = Tracker.pretrained("3dlast")
    assert frame_origin(guarded.net, z).eq(0).all()
    got = guarded.track(z)[keys.STATE]
    ref, _ = guarded.net.rollout(z.float())
    assert got.dtype == torch.float64
    torch.testing.assert_close(got[:, 5:], ref[keys.STATE][:, 5:].double(), rtol=0, atol=0, equal_nan=True)


def _csv(path, z, shift):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["track_id", "t", "x", "y", "z"])
        for b in range(z.shape[0]):
            for k in range(z.shape[1]):
                row = z[b, k] + shift
                w.writerow([f"t{b}", repr(float(k)), *(("",) * 3 if np.isnan(row).any() else map(repr, row.tolist()))])


def _read(path):
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    cols = [c for c in rows[0] if c not in ("track_id", "t")]
    return np.array([[math.nan if r[c] == "" else float(r[c]) for c in cols] for r in rows]), cols


@pytest.mark.parametrize("weights", [[], ["--weights", "3dlast", "--guard", "none"]], ids=["bank", "fixed-grid"])
def test_immnet_track_of_a_shifted_csv_is_shifted(tmp_path, z, weights):
    """Through ``immnet track``: the bank (each row at its own time, ``track_rows``) and a network trained at one
    interval (the fixed grid, ``track_segments``), a CSV far from the radar's origin gives the positions of the CSV
    at it plus the shift (the CSV's 6 decimals), the rest as there."""
    out = {}
    for name, shift in (("ref", np.zeros(3)), ("got", SHIFT.numpy())):
        _csv(tmp_path / f"{name}.csv", z.numpy(), shift)
        assert main(["track", "--input", str(tmp_path / f"{name}.csv"), "--output", str(tmp_path / f"out-{name}.csv"),
                     *weights]) == 0
        out[name] = _read(tmp_path / f"out-{name}.csv")
    (got, cols), (ref, _) = out["got"], out["ref"]
    at = [cols.index(c) for c in ("x", "y", "z")]
    want = ref.copy()
    want[:, at] += SHIFT.numpy()
    assert np.isfinite(got[:, at]).sum() > 60
    np.testing.assert_allclose(got[:, at], want[:, at], rtol=0, atol=1e-3)
    rest = [i for i in range(len(cols)) if i not in at]
    np.testing.assert_allclose(got[:, rest], ref[:, rest], rtol=1e-4, atol=1e-5)
