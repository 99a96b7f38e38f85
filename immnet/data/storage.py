"""3D-LAST data sets on disk: a memory-mapped TensorDict directory, or an ``.npz`` interchange file.

Sets of real flights (:mod:`immnet.data.real`, format ``adsb``) share the directory layout; they are
written whole by :func:`write_arrays`.

A data set directory::

    DIR/meta.json      spec version, seed, n, single_mode, every DataSpec parameter, counts per mode, dtypes
    DIR/tensors/       TensorDict.memmap_ layout (tensordict's own meta.json + one .memmap file per key)

Floats are stored as float32 (positions of tens of km keep ~2 mm resolution, far below the
1-7 m measurement noise), except the scan times ``t [N, T]`` in float64 (epoch times of 1.7e9 s keep
their hundredths of a second; a directory written before ``t`` existed has none, and its scans are at
``k dt``); ``mode`` as int64, so that a loaded set stays lazily memory-mapped
with int64 labels (int8 would save 280 MB per 100k x 400 but need a cast of every read). Generation writes block by
block straight into a preallocated memmap (peak memory bounded by one block, whatever ``n``),
in a temporary sibling directory renamed into place only once complete; an exception, SIGTERM or
SIGINT removes it, and the next writer of the same output removes one left by a killed run
(``kill -9``; see :mod:`immnet.data.scratch`).

The ``.npz`` interchange format (docs/data.md): ``measurements [N,T,3]`` (NaN = missed
detection), optional ``states [N,T,9]`` (a NaN row: no truth at that scan), ``mode [N,T]``
(-1: no label), ``turn_rate [N,T]`` (rad/s), ``r [N]``, ``t [N,T]`` (scan times, s; absent: scans at
``k dt``), ``meas_cov [N,T,3,3]`` (each detection's measurement covariance, m^2, NaN where missed; optional) and
``dt`` (scalar; absent: the median spacing of ``t`` per track where ``t`` is given, else 1). Both
formats are checked on loading by :func:`immnet.data.contract.check_arrays`; an ``.npz`` is read
with ``allow_pickle=False`` (nothing in it is executed).
"""

from __future__ import annotations

import contextlib
import json
import math
import multiprocessing as mp
import zipfile
import zlib
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from immnet import keys
from immnet.data.contract import TRAIL, check_arrays, trailing_shape
from immnet.data.generate import BLOCK, generate_block, mode_index, n_blocks
from immnet.data.scratch import check_space, check_writable, publishing, reserve
from immnet.data.spec import SPEC_VERSION, DataSpec
from immnet.data.times import nominal_dt
from immnet.motion import MODE_NAMES, N_MODES
from immnet.progress import progress as progress_bar

META = "meta.json"
TENSORS = "tensors"
FORMAT = "3d-last"
REAL_FORMAT = "adsb"
"""The format tag of a set of real flights seen by a simulated radar (:mod:`immnet.data.real`)."""
FORMATS = (FORMAT, REAL_FORMAT)


def sample_digests(meta: dict) -> set[str]:
    """The SHA-256 of each sample file a real-flight set's ``meta.json`` names (``samples``): two sets that share one
    name the same flights by the same ids."""
    return {s.get("sha256") for s in meta.get("samples", []) if isinstance(s, dict)}


STORE_DTYPES = {
    keys.STATES: torch.float32, keys.MEASUREMENTS: torch.float32, keys.MODE: torch.int64,
    keys.TURN_RATE: torch.float32, keys.R: torch.float32, keys.DT: torch.float32, keys.TIME: torch.float64,
}
"""The tensors every generated data set holds, and their stored dtypes."""
ALL_DTYPES = {**STORE_DTYPES, keys.MEAS_COV: torch.float32}
"""Every tensor a data set may hold and its stored dtype: ``STORE_DTYPES`` and the detection covariances
``meas_cov`` of a radar's plots (a generated set of plots; real flights', written whole by ``write_arrays``)."""


def store_dtypes(spec: DataSpec) -> dict:
    """The tensors a generated set of ``spec`` holds, and their stored dtypes: ``STORE_DTYPES``, and ``meas_cov``
    where the measurements are a radar's plots (``ALL_DTYPES``)."""
    return ALL_DTYPES if spec.plots else STORE_DTYPES


# --- writing ----------------------------------------------------------------------------------
def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} exists and is not a directory")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"{out} exists and is not empty (pass overwrite=True / --overwrite)")


def _allocate(tensors_dir: Path, n: int, T: int, out: Path, dtypes: dict = STORE_DTYPES) -> None:
    """The data set's files (the keys of ``dtypes``) of ``n`` trajectories of ``T`` scans in ``tensors_dir``, their
    disk blocks allocated (:func:`immnet.data.scratch.reserve`): the blocks are then written through memory maps,
    where a full disk would be a SIGBUS. An ``OSError`` naming ``out``'s folder where the disk lacks the room."""
    shapes = {key: trailing_shape(key, T) for key in dtypes}
    size = {key: n * math.prod(trail) * dtypes[key].itemsize for key, trail in shapes.items()}
    check_space(out.parent, sum(size.values()), f"the data set ({n} trajectories of {T} scans)")
    td = TensorDict({}, batch_size=[n])
    td.memmap_(tensors_dir)
    for key, trail in shapes.items():
        reserve(td.make_memmap(key, shape=[n, *trail], dtype=dtypes[key]).filename, size[key])


_WORKER: dict = {}


def shard_blocks(n: int, index: int, count: int) -> range:
    """The blocks of shard ``index`` of ``count`` of a data set of ``n`` trajectories.

    With ``B = ceil(n / BLOCK)`` blocks, shard ``i`` of ``K`` holds blocks
    ``[floor(i B / K), floor((i + 1) B / K))``: contiguous, whole blocks, sizes differing by at
    most one block, every block in exactly one shard. ``K`` may not exceed ``B`` (no empty shard).
    """
    n, index, count = int(n), int(index), int(count)
    if count < 1:
        raise ValueError(f"the shard count must be >= 1, got {count}")
    if not 0 <= index < count:
        raise ValueError(f"shard index {index} is out of range for {count} shards (valid: 0..{count - 1})")
    nb = n_blocks(n)
    if count > nb:
        raise ValueError(f"{n} trajectories make {nb} block(s) of {BLOCK}; they cannot be split into "
                         f"{count} shards (at most {nb})")
    return range(index * nb // count, (index + 1) * nb // count)


def _block_rows(blocks: range, n: int) -> tuple[int, int]:
    """``(start, stop)``: the trajectories held by a contiguous range of blocks of a set of ``n``."""
    return blocks[0] * BLOCK, min(int(n), blocks[-1] * BLOCK + BLOCK)


def shard_rows(n: int, index: int, count: int) -> tuple[int, int]:
    """``(start, stop)``: the trajectories of shard ``index`` of ``count`` (see :func:`shard_blocks`)."""
    return _block_rows(shard_blocks(n, index, count), n)


def _rows(filename, dtype, trail, start: int, m: int, mode: str) -> np.memmap:
    """Rows ``[start, start + m)`` of one ``.memmap`` file of trailing shape ``trail``, mapped alone."""
    dtype = np.dtype(dtype)
    row = dtype.itemsize * int(np.prod(trail, dtype=np.int64))
    return np.memmap(filename, dtype=dtype, mode=mode, offset=start * row, shape=(m, *trail))


def _init_worker(tensors_dir, seed, n, spec_dict, single_mode, row0):
    torch.set_num_threads(1)  # elementwise ops on ~4k elements: one thread is fastest
    td = TensorDict.load_memmap(tensors_dir)
    spec = DataSpec.from_dict(spec_dict)
    dtypes = store_dtypes(spec)
    files = {k: (td[k].filename, tuple(td[k].shape[1:])) for k in dtypes}
    _WORKER.update(files=files, seed=seed, n=n, spec=spec, single=single_mode, row0=row0, dtypes=dtypes)


def _write_block(b: int) -> list[int]:
    """Generate block ``b`` into the preallocated files; return its label counts per mode.

    Block ``b`` goes to rows ``b * BLOCK - row0`` on (``row0``: the first row of a shard, else 0).
    Each block maps only its own rows (``np.memmap`` with an offset) and unmaps them once
    written, so that the resident memory of a writer stays one block whatever ``n``.
    """
    w = _WORKER
    block = generate_block(w["seed"], b, w["n"], w["spec"], w["single"])
    m, start = block.batch_size[0], b * BLOCK - w["row0"]
    for key, dtype in w["dtypes"].items():
        filename, trail = w["files"][key]
        a = block[key].to(dtype).numpy()
        mm = _rows(filename, a.dtype, trail, start, m, "r+")
        mm[:] = a
        mm.flush()
        del mm
    return torch.bincount(block[keys.MODE].flatten(), minlength=N_MODES).tolist()


def _meta(seed: int, n: int, spec_dict: dict, single_mode, counts, shard: dict | None = None) -> dict:
    """A data set's ``meta.json`` (``shard`` only for one shard of a larger whole); ``spec_dict`` a
    ``DataSpec.to_dict()``."""
    meta = {
        "format": FORMAT, "spec_version": SPEC_VERSION, "seed": int(seed), "n": int(n), "T": int(spec_dict["T"]),
        "single_mode": single_mode, "block": BLOCK, "spec": spec_dict,
        "counts_per_mode": dict(zip(MODE_NAMES, counts)),
        "dtype": {k: str(v).removeprefix("torch.") for k, v in store_dtypes(DataSpec.from_dict(spec_dict)).items()},
    }
    if shard is not None:
        meta["shard"] = shard
    return meta


def _write_meta(directory: Path, meta: dict) -> None:
    (directory / META).write_text(json.dumps(meta, indent=1, allow_nan=False) + "\n")  # strict JSON


def write_arrays(directory, arrays: dict, meta: dict) -> Path:
    """Write whole arrays (numpy ``[N, ...]``, the keys of ``ALL_DTYPES``) as the data set directory
    ``directory`` (created; it must not exist: the caller writes it inside a :func:`publishing` sibling).

    The arrays are checked (:func:`immnet.data.contract.check_arrays`) and stored in ``ALL_DTYPES``;
    ``meta`` (which names its ``format``) gets ``n``, ``T``, ``counts_per_mode`` and ``dtype`` added.
    """
    directory = Path(directory)
    n, T = check_arrays(arrays, str(directory))
    data = {k: torch.from_numpy(np.ascontiguousarray(np.asarray(arrays[k]))).to(ALL_DTYPES[k])
            for k in ALL_DTYPES if k in arrays}
    directory.mkdir()
    check_space(directory, sum(t.nbytes for t in data.values()), f"the data set ({n} trajectories)")  # memmap_ maps
    TensorDict(data, batch_size=[n]).memmap_(directory / TENSORS)
    counts = _mode_counts(data[keys.MODE]) if keys.MODE in data else [0] * N_MODES
    meta = {**meta, "n": int(n), "T": int(T), "counts_per_mode": dict(zip(MODE_NAMES, counts)),
            "dtype": {k: str(v).removeprefix("torch.") for k, v in ALL_DTYPES.items() if k in data}}
    _write_meta(directory, meta)
    return directory


def write_dataset(out, n: int, seed: int, spec: DataSpec = DataSpec(), single_mode: str | None = None,
                  overwrite: bool = False, workers: int = 1, progress: bool = False,
                  shard: tuple[int, int] | None = None) -> Path:
    """Generate ``n`` trajectories from ``seed`` into the data set directory ``out``; return ``out``.

    ``workers`` processes each generate whole blocks into the same preallocated memmap; the
    bytes are identical for any ``workers``. ``out`` must be absent or empty unless ``overwrite``.

    ``shard=(i, K)`` writes only shard ``i`` of ``K`` of those ``n`` (the blocks of
    :func:`shard_blocks`) as a complete data set of its own, its ``meta.json`` saying which
    shard of which whole it is; :func:`immnet.data.shards.merge_shards` joins the ``K`` shards
    into the very bytes of the unsharded set.
    """
    out = Path(out)
    n, workers = int(n), int(workers)
    if n <= 0:
        raise ValueError(f"n must be a positive number of trajectories, got {n}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    mode_index(single_mode)  # validates the name
    blocks = list(range(n_blocks(n)) if shard is None else shard_blocks(n, *shard))
    row0, row1 = _block_rows(blocks, n)
    _check_out(out, overwrite)
    check_writable(out, "folder")
    with publishing(out) as tmp:
        tmp.mkdir()
        _allocate(tmp / TENSORS, row1 - row0, spec.T, out, store_dtypes(spec))
        counts = [0] * N_MODES
        bar = progress_bar(total=row1 - row0, desc=f"3D-LAST -> {out.name}", unit="traj", disable=not progress)
        init = (str(tmp / TENSORS), seed, n, spec.to_dict(), single_mode, row0)
        with contextlib.ExitStack() as stack:
            if workers == 1 or len(blocks) == 1:
                stack.callback(_WORKER.clear)
                stack.callback(torch.set_num_threads, torch.get_num_threads())
                _init_worker(*init)
                results = map(_write_block, blocks)
            else:
                pool = stack.enter_context(mp.get_context("spawn").Pool(
                    min(workers, len(blocks)), initializer=_init_worker, initargs=init))
                results = pool.imap(_write_block, blocks)
            for b, c in zip(blocks, results):
                counts = [a + x for a, x in zip(counts, c)]
                bar.update(min(BLOCK, n - b * BLOCK))
        bar.close()
        info = None if shard is None else {"index": int(shard[0]), "count": int(shard[1]), "n_total": n,
                                           "rows": [row0, row1], "blocks": [blocks[0], blocks[-1] + 1]}
        _write_meta(tmp, _meta(seed, row1 - row0, spec.to_dict(), single_mode, counts, info))
    return out


# --- reading ----------------------------------------------------------------------------------
def _count(value) -> bool:
    """Whether a meta.json value is a whole number >= 0 (JSON's integers; not a bool, a float or a string)."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _check_meta_types(meta: dict, meta_path: Path) -> None:
    """A ValueError naming ``meta_path`` and the field, for a ``n``, ``T`` or ``spec_version`` that is not a whole
    number >= 0, or a ``counts_per_mode`` that is not an object of such numbers by mode name."""
    for k in ("n", "T", "spec_version"):
        if k in meta and not _count(meta[k]):
            raise ValueError(f"{meta_path}: field {k!r} is {_shown(meta[k])}, expected a whole number >= 0")
    counts = meta["counts_per_mode"]
    if not (isinstance(counts, dict) and all(_count(c) for c in counts.values())):
        raise ValueError(f"{meta_path}: field 'counts_per_mode' is {_shown(counts)}, expected an object of label "
                         f"counts by mode name ({', '.join(MODE_NAMES)})")


def _shown(value, width: int = 60) -> str:
    text = json.dumps(value)
    return text if len(text) <= width else text[: width - 3] + "..."


def read_json(path: Path, where=None):
    """The JSON value of the file ``path``; a ValueError beginning with ``where`` (default the file) where the file
    cannot be read or holds no JSON."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{where or path}: not readable as JSON ({type(err).__name__}: {err})") from None


def _load_dir(path: Path) -> tuple[TensorDict, dict]:
    meta_path = path / META
    if not meta_path.exists():
        raise FileNotFoundError(f"{path} is not a 3D-LAST data set: {META} is missing")
    meta = read_json(meta_path)
    if not isinstance(meta, dict) or meta.get("format") not in FORMATS:
        got = meta.get("format") if isinstance(meta, dict) else meta
        raise ValueError(f"{meta_path}: format is {got!r}, expected one of {', '.join(map(repr, FORMATS))}")
    for k in ("n", "T", "counts_per_mode"):
        if k not in meta:
            raise ValueError(f"{meta_path}: field {k!r} is missing")
    _check_meta_types(meta, meta_path)
    if meta.get("spec_version", -1) > SPEC_VERSION:
        raise ValueError(f"{meta_path}: spec version {meta.get('spec_version')} is newer than {SPEC_VERSION}")
    if not (path / TENSORS).is_dir():
        raise FileNotFoundError(f"{path}: the tensors directory {TENSORS}/ is missing")
    td = map_tensors(path / TENSORS)
    n, T = meta["n"], meta["T"]
    if tuple(td.batch_size) != (n,):
        raise ValueError(f"{path}: {META} says n={n} but the tensors hold {tuple(td.batch_size)}")
    arrays = {k: td[k].numpy() for k in (*TRAIL, keys.DT) if k in td.keys()}
    if arrays.get(keys.MEASUREMENTS) is not None and tuple(arrays[keys.MEASUREMENTS].shape[1:2]) != (T,):
        raise ValueError(f"{path}: {META} says T={T} but 'measurements' has shape "
                         f"{tuple(arrays[keys.MEASUREMENTS].shape)}")
    check_arrays(arrays, str(path))
    if keys.MODE in td.keys():
        counts = _mode_counts(td[keys.MODE])
        expected = [int(meta["counts_per_mode"].get(name, 0)) for name in MODE_NAMES]
        if counts != expected:
            raise ValueError(f"{path}: mode counts {counts} do not match {META}'s counts_per_mode {expected}")
    return td, meta


def tensor_files(tensors_dir) -> tuple[dict[str, tuple[Path, torch.dtype, tuple[int, ...]]], int]:
    """``({key: (file, dtype, shape)}, n)``: the tensors of a data set's ``tensors/`` directory, read from its
    ``meta.json`` (JSON only). A ValueError for anything but the data set's own tensors (``ALL_DTYPES``, each in
    its dtype, ``[n, ...]``, in its file ``<key>.memmap`` of that many bytes): tensordict stores any other field as
    a pickle, which runs code when it is loaded, so such a directory is refused before anything in it is read."""
    tensors_dir = Path(tensors_dir)
    where = tensors_dir / META
    meta = read_json(where)
    if not isinstance(meta, dict) or not isinstance(meta.get("shape"), list) or len(meta["shape"]) != 1:
        raise ValueError(f"{where}: not the meta of a data set's tensors (no batch shape [n])")
    n = meta["shape"][0]
    if not isinstance(n, int) or n < 0:
        raise ValueError(f"{where}: batch shape {meta['shape']} is not [n]")
    out = {}
    for key, entry in meta.items():
        if key in ("shape", "device") or key.startswith("_"):  # tensordict's own: "_type" (never read)
            continue
        if key not in ALL_DTYPES:
            raise ValueError(f"{where}: holds {key!r}, not one of a data set's tensors ({', '.join(ALL_DTYPES)}); "
                             f"refused unread (tensordict would unpickle such a field, running code from the file)")
        want = str(ALL_DTYPES[key])
        shape = entry.get("shape") if isinstance(entry, dict) else None
        if (not isinstance(entry, dict) or entry.get("dtype") != want or entry.get("is_nested", False)
                or not isinstance(shape, list) or not shape or shape[0] != n
                or not all(isinstance(d, int) and d >= 0 for d in shape)):
            raise ValueError(f"{where}: {key!r} is {entry!r}, expected a {want} tensor of shape [{n}, ...]")
        file = tensors_dir / f"{key}.memmap"
        size = math.prod(shape) * ALL_DTYPES[key].itemsize
        got = file.stat().st_size if file.is_file() else None
        if got != size:
            raise ValueError(f"{file}: " + ("missing" if got is None else f"{got} bytes, {key!r} {shape} needs {size}"))
        out[key] = (file, ALL_DTYPES[key], tuple(shape))
    return out, n


def map_tensors(tensors_dir) -> TensorDict:
    """A data set's ``tensors/`` directory as a TensorDict ``[n]`` of its files mapped copy-on-write
    (``tensor_files`` checks them first): pages are read as they are used, and writing into a loaded tensor
    changes the process's copy, never the file."""
    files, n = tensor_files(tensors_dir)
    out = {}
    for key, (file, dtype, shape) in files.items():
        numel = math.prod(shape)
        out[key] = (torch.from_file(str(file), shared=False, dtype=dtype, size=numel).view(shape) if numel
                    else torch.empty(shape, dtype=dtype))
    return TensorDict(out, batch_size=[n])


def _mode_counts(mode: torch.Tensor) -> list[int]:
    """Labels per mode (``NO_LABEL`` scans not counted), in ``MODE_NAMES`` order."""
    counts = torch.bincount(mode.flatten().to(torch.int64) + 1, minlength=N_MODES + 1)  # checked >= -1
    return counts[1:].tolist()


_NPZ_DTYPES = {keys.MODE: np.int64, keys.TIME: np.float64}
"""The arrays of an ``.npz`` read in other dtypes than float32: ``mode``, and the scan times (epoch times keep their
hundredths of a second)."""
# what np.load raises on a file that is not a whole .npz (truncated, empty, corrupt member, pickled object)
_UNREADABLE = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error)


def read_npz(path: Path, keys_read) -> tuple[dict, list[str]]:
    """``(arrays, names)``: those of the arrays ``keys_read`` that the ``.npz`` file ``path`` holds, and the names of
    all it holds, read with ``allow_pickle=False`` (nothing in it is executed); a ValueError naming the file where it
    is not a whole archive of named arrays."""
    try:
        with open(path, "rb") as f:  # ours to close, whatever np.load raises
            z = np.load(f, allow_pickle=False)
            if not isinstance(z, np.lib.npyio.NpzFile):
                raise ValueError("it holds one bare array, not an archive of named arrays")
            return {k: z[k] for k in keys_read if k in z.files}, list(z.files)
    except _UNREADABLE as err:
        raise ValueError(f"{path}: not a readable .npz file ({type(err).__name__}: {err})") from None


def _load_npz(path: Path) -> tuple[TensorDict, dict]:
    arrays, names = read_npz(path, (*TRAIL, keys.DT))
    if keys.MEASUREMENTS not in arrays:
        raise ValueError(f"{path}: the required array 'measurements' [N,T,3] is missing (has {names})")
    if keys.DT in arrays and arrays[keys.DT].size != 1:
        raise ValueError(f"{path}: array 'dt' has shape {arrays[keys.DT].shape}, expected a scalar")
    given_dt = keys.DT in arrays
    if not given_dt:
        arrays[keys.DT] = np.asarray(1.0)
    n, T = check_arrays(arrays, str(path))
    dt = float(arrays.pop(keys.DT).reshape(()))
    data = {key: torch.from_numpy(np.ascontiguousarray(a, dtype=_NPZ_DTYPES.get(key, np.float32)))
            for key, a in arrays.items()}
    if given_dt or keys.TIME not in data:
        data[keys.DT] = torch.full((n,), dt, dtype=torch.float32)
    else:  # scan times without a nominal interval: the median spacing per track
        data[keys.DT] = nominal_dt(TensorDict({keys.TIME: data[keys.TIME]}, batch_size=[n])).to(torch.float32)
        dt = float(data[keys.DT].median())
    td = TensorDict(data, batch_size=[n])
    counts = dict(zip(MODE_NAMES, _mode_counts(data[keys.MODE]))) if keys.MODE in data else None
    meta = {"format": "npz", "source": str(path), "n": int(n), "T": int(T), "dt": dt,
            "keys": sorted(data), "counts_per_mode": counts}
    return td, meta


def load_dataset(path) -> tuple[TensorDict, dict]:
    """A data set directory or ``.npz`` file -> ``(TensorDict [N], meta)``.

    A directory's tensors are mapped copy-on-write (``map_tensors``: writing into them never reaches the files;
    nothing but the set's own tensors is read, no pickle ever) (floats float32, ``mode`` int64); an ``.npz`` is
    read into memory (floats float32, ``mode`` int64). Only the keys present are returned. Every
    array is checked (:func:`immnet.data.contract.check_arrays`): a ValueError names what is wrong.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no data set at {path}")
    if path.is_dir():
        return _load_dir(path)
    if path.suffix == ".npz":
        return _load_npz(path)
    raise ValueError(f"{path}: expected a data set directory or an .npz file")


def as_batch(td: TensorDict, float_dtype=torch.float32) -> TensorDict:
    """A loaded (memmapped) slice as plain tensors: floats in ``float_dtype`` except the scan times ``t``
    (float64 whatever ``float_dtype``), ``mode`` int64."""
    fixed = {keys.MODE: torch.int64, keys.TIME: torch.float64}  # scan times stay float64 (epoch times)
    return TensorDict({key: v.to(fixed[key]) if key in fixed else v.to(float_dtype) if v.is_floating_point() else v
                       for key, v in td.items()}, batch_size=td.batch_size)


def export_npz(path_in, out_npz) -> Path:
    """Write a data set (directory or ``.npz``) as one ``.npz`` interchange file, atomically."""
    out_npz = Path(out_npz)
    if out_npz.suffix != ".npz":
        raise ValueError(f"{out_npz}: the output must end in .npz")
    check_writable(out_npz)
    td, meta = load_dataset(path_in)
    arrays = {key: td[key].numpy() for key in TRAIL if key in td.keys()}  # mode: int64 as loaded
    dts = td[keys.DT] if keys.DT in td.keys() else torch.ones(1)
    if keys.TIME not in td.keys() or bool((dts == dts[0]).all()):
        arrays[keys.DT] = np.asarray(float(dts[0]))
    # else: nominal intervals that differ per track are not a scalar; the reader takes each track's median
    # spacing of ``t``, which is what a loaded .npz without ``dt`` holds
    with publishing(out_npz, suffix=".npz") as tmp:
        np.savez(tmp, **arrays)
    return out_npz
