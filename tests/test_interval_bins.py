"""``scripts/interval_bins.py`` (docs/results.md "The general model"): each method's Average RMSE by the scan's
interval, checked against numpy on a generated set with irregular scans."""

import runpy

import numpy as np
import pytest

from immnet import keys
from immnet.config import REPO_ROOT
from immnet.data.spec import DataSpec
from immnet.data.storage import as_batch, load_dataset, write_dataset

SCRIPT = REPO_ROOT / "scripts" / "interval_bins.py"


def test_the_raw_measurements_by_interval_equal_numpy(tmp_path, capsys):
    """The raw measurements' error (each scan's measurement, or the last one where the scan missed, minus the
    truth, from the track's first detection) binned by the time since the scan before (scan 0: the nominal
    interval), each axis's RMSE averaged over x, y, z, as numpy computes it."""
    data = write_dataset(tmp_path / "irregular", 12, 3, DataSpec(T=120, dt=2.0, dt_jitter=1.5, p_miss=0.1),
                         progress=False)
    main = runpy.run_path(str(SCRIPT))["main"]
    assert main(["--data", str(data), "--methods", "measurements", "--edges", "0.5,1.5,2.5,3.5"]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("| measurements"))
    ours = [float(v) for v in row.strip("| ").split("|")[1:]]

    batch = as_batch(load_dataset(data)[0])
    t = batch[keys.TIME].double().numpy()
    dt = np.concatenate([np.full((t.shape[0], 1), 2.0), np.diff(t, axis=1)], axis=1)
    z = batch[keys.MEASUREMENTS].double().numpy()
    truth = batch[keys.STATES].double().numpy()[..., [0, 3, 6]]
    detected = np.isfinite(z).all(-1)
    last = np.maximum.accumulate(np.where(detected, np.arange(z.shape[1]), 0), axis=1)
    held = np.take_along_axis(z, last[..., None], axis=1)  # a missed detection holds the last measurement
    err = held - truth
    started = np.maximum.accumulate(detected, axis=1)
    expect = []
    for lo, hi, last in ((0.5, 1.5, False), (1.5, 2.5, False), (2.5, 3.5, True)):
        sel = started & (dt >= lo) & ((dt <= hi) if last else (dt < hi))
        assert sel.sum() > 100
        e = err[sel]
        expect.append(np.sqrt((e ** 2).mean(0)).mean())
    assert ours == pytest.approx(expect, abs=6e-4)  # the table's three decimals


def test_knock_out_adds_a_row_for_each_learned_part_of_the_network(tmp_path, capsys):
    """``--knock-out immnet-general``: the default network and, beside it, the same weights with each learned part
    (KalmanNet, the Transformer) and both knocked out (``IMMNet.learned_parts``, ``scripts/learned_parts.py``'s
    variants); with both out it is IMMNet with nothing learned, which tracks differently from the trained network."""
    data = write_dataset(tmp_path / "irregular", 4, 5, DataSpec(T=40, dt=2.0, dt_jitter=1.5, min_segment=12),
                         progress=False)
    main = runpy.run_path(str(SCRIPT))["main"]
    assert main(["--data", str(data), "--methods", "immnet-general", "--knock-out", "immnet-general",
                 "--edges", "0.5,2,3.5"]) == 0
    rows = {line.split("|")[1].strip(): [float(v) for v in line.strip("| ").split("|")[1:]]
            for line in capsys.readouterr().out.splitlines() if line.startswith("| immnet-general")}
    assert list(rows) == ["immnet-general", "immnet-general - KalmanNet (filters at base noise)",
                          "immnet-general - Transformer (IMM mode update alone)",
                          "immnet-general - both (nothing learned)"]
    assert all(len(v) == 2 and np.isfinite(v).all() for v in rows.values())
    assert rows["immnet-general - both (nothing learned)"] != rows["immnet-general"]
