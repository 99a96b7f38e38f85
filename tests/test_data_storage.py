"""Data sets on disk: memmapped directories, .npz interchange, atomic writes, clear errors."""

import json

import numpy as np
import pytest
import torch

from immnet.data import storage
from immnet.data.generate import BLOCK, generate
from immnet.data.spec import DataSpec
from immnet.data.storage import export_npz, load_dataset, write_dataset

SPEC = DataSpec(T=50, min_segment=10)


def _leftovers(d):
    return [p.name for p in d.iterdir() if ".tmp-" in p.name]


def test_write_load_matches_generate_float32(tmp_path):
    out = write_dataset(tmp_path / "ds", 300, seed=4, spec=SPEC)
    td, meta = load_dataset(out)
    ref = generate(300, 4, SPEC)
    assert td.batch_size == torch.Size([300])
    for k in ref.keys():
        want = ref[k].to(torch.float32) if ref[k].is_floating_point() else ref[k]
        assert td[k].dtype == want.dtype
        assert torch.equal(td[k].contiguous(), want), k
    assert meta["spec_version"] == 1 and meta["seed"] == 4 and meta["n"] == 300
    assert meta["spec"] == SPEC.to_dict() and meta["single_mode"] is None
    assert sum(meta["counts_per_mode"].values()) == 300 * 50
    assert meta["dtype"]["states"] == "float32"


def test_workers_do_not_change_bytes(tmp_path):
    n = BLOCK + 150  # two blocks
    a = write_dataset(tmp_path / "a", n, seed=2, spec=SPEC)
    b = write_dataset(tmp_path / "b", n, seed=2, spec=SPEC, workers=2)
    ta, _ = load_dataset(a)
    tb, _ = load_dataset(b)
    for k in ta.keys():
        assert ta[k].numpy().tobytes() == tb[k].numpy().tobytes(), k
    assert (a / "meta.json").read_text() == (b / "meta.json").read_text()


def test_existing_output_and_overwrite(tmp_path):
    out = tmp_path / "ds"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    with pytest.raises(FileExistsError, match="not empty"):
        write_dataset(out, 10, 0, SPEC)
    assert (out / "keep.txt").exists()
    write_dataset(out, 10, 0, SPEC, overwrite=True)
    assert not (out / "keep.txt").exists()
    assert load_dataset(out)[0].batch_size == torch.Size([10])
    assert _leftovers(tmp_path) == []


def test_failure_leaves_no_partial_output(tmp_path, monkeypatch):
    def boom(*a, **k):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(storage, "generate_block", boom)
    with pytest.raises(RuntimeError):
        write_dataset(tmp_path / "ds", 10, 0, SPEC)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="valid modes"):
        write_dataset(tmp_path / "ds", 10, 0, SPEC, single_mode="zigzag")
    assert list(tmp_path.iterdir()) == []


def test_npz_round_trip_with_nan(tmp_path):
    out = write_dataset(tmp_path / "ds", 40, seed=1, spec=SPEC, single_mode="ct-")
    npz = export_npz(out, tmp_path / "x.npz")
    td, meta = load_dataset(npz)
    ref, _ = load_dataset(out)
    for k in ref.keys():
        assert torch.equal(td[k], ref[k].contiguous()), k
    assert meta["T"] == 50 and meta["n"] == 40
    # measurements only, with missed detections, float64 and dt
    z = np.random.default_rng(0).normal(size=(5, 30, 3))
    z[1, 3] = np.nan
    np.savez(tmp_path / "m.npz", measurements=z, dt=np.float64(0.5))
    td, meta = load_dataset(tmp_path / "m.npz")
    assert set(td.keys()) == {"measurements", "dt"}
    assert torch.isnan(td["measurements"][1, 3]).all() and (td["dt"] == 0.5).all()
    export_npz(tmp_path / "m.npz", tmp_path / "m2.npz")
    z2 = np.load(tmp_path / "m2.npz")
    assert np.array_equal(np.isnan(z2["measurements"]), np.isnan(z)) and float(z2["dt"]) == 0.5
    assert set(z2.files) == {"measurements", "dt"}
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize(
    "arrays, msg",
    [
        ({"states": np.zeros((2, 5, 9))}, "'measurements'.*missing"),
        ({"measurements": np.zeros((2, 5))}, r"'measurements' has shape \(2, 5\)"),
        ({"measurements": np.zeros((2, 5, 3)), "states": np.zeros((2, 5, 6))}, r"'states' has shape \(2, 5, 6\)"),
        ({"measurements": np.zeros((2, 5, 3)), "mode": np.zeros((2, 4), int)}, r"'mode' has shape \(2, 4\)"),
        ({"measurements": np.zeros((2, 5, 3)), "r": np.zeros(3)}, r"'r' has shape \(3,\)"),
        ({"measurements": np.zeros((2, 5, 3)), "dt": np.ones(2)}, "'dt'.*scalar"),
    ],
    ids=["no-measurements", "bad-measurements", "bad-states", "bad-mode", "bad-r", "bad-dt"],
)
def test_npz_errors_name_the_array(tmp_path, arrays, msg):
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match=msg):
        load_dataset(tmp_path / "bad.npz")


def test_directory_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_dataset(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="meta.json"):
        load_dataset(tmp_path / "empty")
    out = write_dataset(tmp_path / "ds", 20, 0, SPEC)
    meta = json.loads((out / "meta.json").read_text())
    bad = dict(meta, counts_per_mode={"cv": 1, "ca": 0, "ct+": 0, "ct-": 0})
    (out / "meta.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="counts"):
        load_dataset(out)
    (out / "meta.json").write_text(json.dumps(dict(meta, n=21)))
    with pytest.raises(ValueError, match="n=21"):
        load_dataset(out)
    (out / "meta.json").write_text("{not json")
    with pytest.raises(ValueError, match="JSON"):
        load_dataset(out)
    with pytest.raises(ValueError, match=".npz"):
        export_npz(out, tmp_path / "x.csv")
