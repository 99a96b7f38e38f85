"""Data sets on disk: memmapped directories, .npz interchange, atomic writes, clear errors."""

import json

import numpy as np
import pytest
import torch

from immnet.data import storage
from immnet.data.generate import BLOCK, generate
from immnet.data.spec import DataSpec
from immnet.data.storage import STORE_DTYPES, export_npz, load_dataset, tensor_files, write_dataset

SPEC = DataSpec(T=50, min_segment=10)


def _leftovers(d):
    return [p.name for p in d.iterdir() if ".tmp-" in p.name]


def test_write_load_matches_generate_float32(tmp_path):
    out = write_dataset(tmp_path / "ds", 300, seed=4, spec=SPEC)
    td, meta = load_dataset(out)
    ref = generate(300, 4, SPEC)
    assert td.batch_size == torch.Size([300])
    for k in ref.keys():
        want = ref[k].to(STORE_DTYPES[k]) if ref[k].is_floating_point() else ref[k]  # t float64, floats float32
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


# --- the contract of a data set's arrays (immnet.data.contract) -------------------------------
def _good(n=3, T=8):
    rng = np.random.default_rng(5)
    return {"measurements": rng.normal(size=(n, T, 3)) * 1e4, "states": rng.normal(size=(n, T, 9)) * 1e4,
            "mode": rng.integers(0, 4, size=(n, T)), "turn_rate": rng.normal(size=(n, T)) * 0.05,
            "r": rng.uniform(1, 7, n), "dt": np.float64(1.0)}


def _with(key, fn):
    def make():
        a = _good()
        a[key] = fn(a[key])
        return a
    return make


def _at(value, idx):
    def fn(a):
        a = a.copy()
        a[idx] = value
        return a
    return fn


BAD_NPZ = {
    "dt-zero": (_with("dt", lambda a: np.float64(0)), r"'dt' is 0; it must be finite and > 0"),
    "dt-negative": (_with("dt", lambda a: np.float64(-0.5)), r"'dt' is -0\.5; it must be finite and > 0"),
    "dt-nan": (_with("dt", lambda a: np.float64(np.nan)), r"'dt' is nan; it must be finite"),
    "dt-inf": (_with("dt", lambda a: np.float64(np.inf)), r"'dt' is inf; it must be finite"),
    "dt-empty": (_with("dt", lambda a: np.array([])), r"'dt' has shape \(0,\), expected a scalar"),
    "T-zero": (lambda: {k: (v[:, :0] if np.ndim(v) >= 2 else v) for k, v in _good().items()},
               r"shape \(3, 0, 3\): a data set needs N >= 1 trajectories of T >= 1 scans"),
    "N-zero": (lambda: {k: (v[:0] if np.ndim(v) >= 1 else v) for k, v in _good().items()},
               r"shape \(0, 8, 3\): a data set needs N >= 1"),
    "mode-7": (_with("mode", _at(7, (2, 5))), r"'mode' holds 7 at \[2, 5\]; valid: 0\.\.3"),
    "mode-minus-2": (_with("mode", _at(-2, (0, 1))), r"'mode' holds -2 at \[0, 1\]"),
    "states-float16": (_with("states", lambda a: a.astype(np.float16)), r"'states' is float16, which rounds"),
    "measurements-float16": (_with("measurements", lambda a: a.astype(np.float16)), r"'measurements' is float16"),
    "r-zero": (_with("r", _at(0.0, 1)), r"'r' at \[1\] is 0; it must be finite and > 0"),
    "r-nan": (_with("r", _at(np.nan, 2)), r"'r' at \[2\] is nan"),
    "states-inf": (_with("states", _at(np.inf, (1, 3, 4))), r"'states' at \[1, 3\] is neither all finite nor all NaN"),
    "states-partly-nan": (_with("states", _at(np.nan, (2, 7, 0))), r"'states' at \[2, 7\] is neither"),
    "turn-rate-inf": (_with("turn_rate", _at(-np.inf, (0, 6))), r"'turn_rate' at \[0, 6\] is -inf"),
    "states-complex": (_with("states", lambda a: a.astype(np.complex64)), r"'states' must be float32 or float64"),
}


@pytest.mark.parametrize("make, msg", list(BAD_NPZ.values()), ids=list(BAD_NPZ))
def test_npz_bad_values_are_refused_by_name(tmp_path, make, msg):
    """Issue 20, item 2: every array's dtype, shape, finiteness and range is checked on loading,
    with a one-line ValueError naming the array, the value and where it is."""
    np.savez(tmp_path / "bad.npz", **make())
    with pytest.raises(ValueError, match=msg) as err:
        load_dataset(tmp_path / "bad.npz")
    assert "\n" not in str(err.value) and str(tmp_path / "bad.npz") in str(err.value)


def _corrupt_member(path):
    """An uncompressed .npz with bytes of its 'measurements' member changed (the CRC no longer fits)."""
    np.savez(path, **_good())
    b = bytearray(path.read_bytes())
    i = b.index(b"measurements.npy") + 200
    b[i : i + 16] = bytes(16)
    path.write_bytes(bytes(b))


UNREADABLE = {
    "empty-file": lambda p: p.write_bytes(b""),
    "truncated": lambda p: (np.savez(p, **_good()), p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])),
    "corrupt-member": _corrupt_member,
    "bare-npy-array": lambda p: p.write_bytes(_npy_bytes(np.zeros((2, 5, 3)))),
    "pickled-object-array": lambda p: np.savez(p, measurements=np.array([object()], dtype=object)),
}


def _npy_bytes(a):
    import io

    f = io.BytesIO()
    np.save(f, a)
    return f.getvalue()


@pytest.mark.parametrize("make", list(UNREADABLE.values()), ids=list(UNREADABLE))
def test_unreadable_npz_is_refused_in_one_line(tmp_path, make):
    """Issue 20, item 2: an empty, truncated or corrupt .npz (or one holding pickles) is refused as
    "not a readable .npz" with a ValueError, not a traceback of zipfile or numpy."""
    path = tmp_path / "x.npz"
    make(path)
    with pytest.raises(ValueError, match=r"x\.npz: not a readable \.npz file \(") as err:
        load_dataset(path)
    assert "\n" not in str(err.value)


def test_npz_padding_is_accepted_and_not_counted(tmp_path):
    """Issue 20, item 3: truth padded with NaN rows after a track's end, and mode -1 (no label)
    there, load as they are; -1 is no label, so counts_per_mode counts only the labelled scans."""
    a = _good()
    a["states"][1, 5:] = np.nan
    a["mode"][1, 5:] = -1
    a["turn_rate"][1, 5:] = np.nan
    np.savez(tmp_path / "p.npz", **a)
    td, meta = load_dataset(tmp_path / "p.npz")
    assert torch.isnan(td["states"][1, 5:]).all() and torch.isfinite(td["states"][1, :5]).all()
    assert (td["mode"][1, 5:] == -1).all()
    want = np.bincount(a["mode"][a["mode"] >= 0], minlength=4)
    assert list(meta["counts_per_mode"].values()) == want.tolist() and sum(want) == 3 * 8 - 3


@pytest.mark.parametrize(
    "key, value, msg",
    [("dt", 0.0, r"'dt' at \[3\] is 0"), ("mode", 9, r"'mode' holds 9 at \[4, 7\]"),
     ("states", float("inf"), r"'states' at \[4, 7\] is neither"), ("r", float("nan"), r"'r' at \[3\] is nan")],
    ids=["dt-zero", "mode-9", "states-inf", "r-nan"],
)
def test_directory_values_are_checked(tmp_path, key, value, msg):
    """Issue 20, item 2: a data set directory's arrays pass the same checks as an .npz (a tensor
    edited on disk is refused by name, not trained or scored on)."""
    out = write_dataset(tmp_path / "ds", 20, 0, SPEC)
    file, _, shape = tensor_files(out / "tensors")[0][key]
    a = np.memmap(file, dtype=str(STORE_DTYPES[key]).removeprefix("torch."), mode="r+", shape=shape)
    idx = 3 if key in ("dt", "r") else (4, 7) if key == "mode" else (4, 7, 1)
    a[idx] = value
    a.flush()
    del a
    with pytest.raises(ValueError, match=msg):
        load_dataset(out)


@pytest.mark.parametrize("field", ["dt", "sigma_q", "r_max", "range_max"])
def test_a_non_finite_spec_is_refused_before_anything_is_written(tmp_path, field):
    """Issue 20, items 2 and 3: a DataSpec field of NaN or inf (``dt: .nan`` in a data config) is
    refused by name, instead of generating a set whose meta.json holds a bare NaN (invalid JSON)."""
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match=rf"DataSpec field '{field}' must be a finite number"):
            DataSpec.from_dict({field: bad})
    out = write_dataset(tmp_path / "ds", 10, 0, SPEC)
    json.loads((out / "meta.json").read_text(), parse_constant=lambda c: pytest.fail(f"meta.json holds {c}"))


# --- scan times t [N, T] (issue 22) -----------------------------------------------------------------
JITTER = DataSpec(T=50, dt=5.0, dt_jitter=0.5, min_segment=10)


def test_scan_times_round_trip_through_directory_and_npz(tmp_path):
    out = write_dataset(tmp_path / "ds", 30, seed=2, spec=JITTER)
    td, meta = load_dataset(out)
    ref = generate(30, 2, JITTER)
    assert td["t"].dtype == torch.float64 and torch.equal(td["t"].contiguous(), ref["t"])  # float64 on disk
    assert meta["spec"]["dt_jitter"] == 0.5 and meta["dtype"]["t"] == "float64"
    batch = storage.as_batch(td[:4])
    assert batch["t"].dtype == torch.float64 and batch["measurements"].dtype == torch.float32
    npz = export_npz(out, tmp_path / "x.npz")
    assert np.load(npz)["t"].dtype == np.float64
    back, _ = load_dataset(npz)
    for k in td.keys():
        assert torch.equal(back[k], td[k].contiguous()), k


def test_npz_scan_times_without_dt_get_the_median_spacing(tmp_path):
    """Epoch times to 0.01 s, no dt: the nominal dt is each track's median spacing, t stays float64."""
    rng = np.random.default_rng(1)
    t = 1.7e9 + np.cumsum(np.round(rng.uniform(4.5, 5.5, size=(4, 21)), 2), axis=1)
    np.savez(tmp_path / "e.npz", measurements=rng.normal(size=(4, 21, 3)), t=t)
    td, meta = load_dataset(tmp_path / "e.npz")
    assert td["t"].dtype == torch.float64 and np.array_equal(td["t"].numpy(), t)
    want = np.median(np.diff(t, axis=1), axis=1)  # 20 spacings: numpy's median averages the middle two
    torch_median = torch.from_numpy(np.diff(t, axis=1)).median(1).values.numpy()  # the lower of the two
    assert np.allclose(td["dt"].numpy(), torch_median.astype(np.float32)) and np.all(np.abs(torch_median - want) < 1)
    np.savez(tmp_path / "d.npz", measurements=rng.normal(size=(4, 21, 3)), t=t, dt=np.float64(5.0))
    assert (load_dataset(tmp_path / "d.npz")[0]["dt"] == 5.0).all()  # a given dt is kept
    export_npz(tmp_path / "e.npz", tmp_path / "e2.npz")  # per-track nominal dt: written as t alone
    z = np.load(tmp_path / "e2.npz")
    assert "dt" not in z.files and np.array_equal(z["t"], t)


def _good_t(n=3, T=8):
    a = _good(n, T)
    a["t"] = np.tile(np.arange(T, dtype=np.float64), (n, 1))
    return a


def _t_with(fn):
    def make():
        a = _good_t()
        a["t"] = fn(a["t"])
        return a
    return make


BAD_T = {
    "t-decreasing": (_t_with(_at(2.5, (1, 4))), r"'t' is not strictly increasing at \[1, 4\]: scan time 2\.5 s follows 3\.0 s"),
    "t-repeated": (_t_with(_at(3.0, (2, 2))), r"'t' is not strictly increasing at \[2, 3\]"),
    "t-nan": (_t_with(_at(np.nan, (0, 6))), r"'t' at \[0, 6\] is nan; scan times must be finite"),
    "t-inf": (_t_with(_at(np.inf, (2, 7))), r"'t' at \[2, 7\] is inf"),
    "t-shape": (_t_with(lambda a: a[:, :5]), r"'t' has shape \(3, 5\), expected \(3, 8\)"),
    "t-1d": (_t_with(lambda a: a[0]), r"'t' has shape \(8,\), expected \(3, 8\)"),
    "t-float16": (_t_with(lambda a: a.astype(np.float16)), r"'t' is float16"),
}


@pytest.mark.parametrize("make, msg", list(BAD_T.values()), ids=list(BAD_T))
def test_malformed_scan_times_are_refused_by_name(tmp_path, make, msg):
    np.savez(tmp_path / "bad.npz", **make())
    with pytest.raises(ValueError, match=msg) as err:
        load_dataset(tmp_path / "bad.npz")
    assert "\n" not in str(err.value)


def test_directory_scan_times_are_checked(tmp_path):
    out = write_dataset(tmp_path / "ds", 20, 0, SPEC)
    file, _, shape = tensor_files(out / "tensors")[0]["t"]
    a = np.memmap(file, dtype=np.float64, mode="r+", shape=shape)
    a[6, 9] = a[6, 8]
    a.flush()
    del a
    with pytest.raises(ValueError, match=r"'t' is not strictly increasing at \[6, 9\]"):
        load_dataset(out)


def test_a_directory_without_scan_times_still_loads(tmp_path):
    """A data set written before t was stored (no t memmap): loads, and its scans are at k dt."""
    import shutil

    from immnet.data.times import scan_intervals

    out = write_dataset(tmp_path / "ds", 20, 0, DataSpec(T=50, dt=5.0, min_segment=10))
    td, _ = load_dataset(out)
    old = storage.as_batch(td.exclude("t")).clone()  # float32 as on disk, mode int64
    del td
    shutil.rmtree(out / "tensors")
    old.memmap_(out / "tensors")
    td, _ = load_dataset(out)
    assert "t" not in td.keys()
    iv = scan_intervals(storage.as_batch(td))
    assert torch.equal(iv, torch.full((20, 50), 5.0, dtype=torch.float64))
    back, _ = load_dataset(export_npz(out, tmp_path / "old.npz"))
    assert "t" not in back.keys() and (back["dt"] == 5.0).all()


def test_writing_into_a_loaded_set_never_reaches_its_files(tmp_path):
    """A tracker or script that edits a loaded batch in place (marks a scan missed) changes its own copy: the data
    set on disk keeps its bytes, and loads as written."""
    out = write_dataset(tmp_path / "ds", 20, 0, SPEC)
    before = {f.name: f.read_bytes() for f in (out / "tensors").iterdir()}
    td, _ = load_dataset(out)
    td["measurements"][2, 5] = float("nan")
    td["states"].mul_(2.0)
    assert torch.isnan(td["measurements"][2, 5]).all()
    assert {f.name: f.read_bytes() for f in (out / "tensors").iterdir()} == before
    again, _ = load_dataset(out)
    assert not torch.isnan(again["measurements"][2, 5]).any()


def test_a_pickled_field_in_a_set_is_refused_unread(tmp_path):
    """tensordict stores a non-tensor field as a pickle and unpickles it on loading; a data set directory holding
    one (or any tensor that is not the set's own) is refused by name before anything in it runs."""
    import os
    import pickle

    sentinel = tmp_path / "ran"

    class Runs:
        def __reduce__(self):
            return (os.system, (f"touch {sentinel}",))

    out = write_dataset(tmp_path / "ds", 20, 0, SPEC)
    tensors = out / "tensors"
    meta = json.loads((tensors / "meta.json").read_text())
    (tensors / "o").mkdir()
    (tensors / "o" / "meta.json").write_text(json.dumps({"_type": "<class 'tensordict.tensorclass.NonTensorData'>",
                                                          "_is_non_tensor": True, "_metadata": None}))
    (tensors / "o" / "other.pickle").write_bytes(pickle.dumps(Runs()))
    (tensors / "meta.json").write_text(json.dumps({**meta, "o": {"type": "NonTensorData"}}))
    with pytest.raises(ValueError, match=r"holds 'o', not one of a data set's tensors"):
        load_dataset(out)
    assert not sentinel.exists()


@pytest.mark.parametrize("edit, msg", [
    (lambda m, d: m["states"].update(dtype="torch.float64"), r"'states' is .*expected a torch.float32 tensor"),
    (lambda m, d: m["r"].update(shape=[19]), r"'r' is .*of shape \[20, \.\.\.\]"),
    (lambda m, d: (d / "r.memmap").write_bytes((d / "r.memmap").read_bytes()[:-4]), r"r.memmap: 76 bytes, 'r' \[20\] needs 80"),
    (lambda m, d: (d / "dt.memmap").unlink(), r"dt.memmap: missing"),
    (lambda m, d: m.update(shape=[20, 2]), r"no batch shape \[n\]"),
], ids=["dtype", "shape", "truncated", "missing", "batch"])
def test_a_tensors_directory_unlike_its_meta_is_refused_by_name(tmp_path, edit, msg):
    out = write_dataset(tmp_path / "ds", 20, 0, SPEC)
    tensors = out / "tensors"
    meta = json.loads((tensors / "meta.json").read_text())
    edit(meta, tensors)
    (tensors / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=msg):
        load_dataset(out)


@pytest.mark.parametrize("field,value,expected", [
    ("n", None, "a whole number >= 0"), ("n", "20", "a whole number >= 0"), ("n", 20.0, "a whole number >= 0"),
    ("n", True, "a whole number >= 0"), ("T", None, "a whole number >= 0"), ("T", -50, "a whole number >= 0"),
    ("spec_version", None, "a whole number >= 0"),
    ("counts_per_mode", [1, 2, 3, 4], "an object of label counts by mode name (cv, ca, ct+, ct-)"),
    ("counts_per_mode", None, "an object of label counts by mode name (cv, ca, ct+, ct-)"),
    ("counts_per_mode", {"cv": "3", "ca": 0, "ct+": 0, "ct-": 0}, "an object of label counts by mode name"),
], ids=["n-null", "n-string", "n-float", "n-bool", "T-null", "T-negative", "spec_version-null", "counts-list",
        "counts-null", "counts-string"])
def test_a_meta_json_field_of_the_wrong_type_is_refused_by_name(tmp_path, field, value, expected, capsys):
    """Issue 60, item 7: a meta.json whose ``n`` is null or a string, or whose ``counts_per_mode`` is a list, ended
    in a TypeError / AttributeError traceback in storage.py (or, for "20", loaded as if it were a number); now one
    line naming the file, the field and its value, from ``load_dataset`` and from ``immnet evaluate`` (exit 2)."""
    from immnet.cli import main

    out = write_dataset(tmp_path / "ds", 20, 0, SPEC)
    meta = json.loads((out / "meta.json").read_text())
    (out / "meta.json").write_text(json.dumps(dict(meta, **{field: value})))
    why = f"{out / 'meta.json'}: field {field!r} is {json.dumps(value)}, expected {expected}"
    with pytest.raises(ValueError) as err:
        load_dataset(out)
    assert str(err.value).startswith(why), str(err.value)
    capsys.readouterr()
    assert main(["evaluate", "--data", str(out), "--split", "all", "--methods", "measurements", "--quiet"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"immnet evaluate: error: {why}"), lines
