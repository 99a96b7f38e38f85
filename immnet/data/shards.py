"""Data sets generated on several machines: ``K`` shards of one ``(seed, n, spec)``, merged into one.

``immnet data generate --n N --seed S --shard i/K --out DIR_i`` writes shard ``i`` of ``K``: the
whole blocks ``[floor(i B / K), floor((i + 1) B / K))`` of the ``B = ceil(N / BLOCK)`` blocks, as a
complete data set whose ``meta.json`` carries ``shard = {index, count, n_total, rows, blocks}``
(see :func:`immnet.data.storage.shard_blocks`). Since every block is seeded from
``(seed, block)`` alone, the shards hold exactly the rows of the unsharded set.

:func:`merge_shards` checks that the shards are the ``K`` pieces of one whole (same seed, spec,
``n``, ``K``; each index once; rows tiling ``[0, N)``) and copies them block by block into a
temporary sibling of the output, renamed into place when complete: the result is byte for byte
what ``immnet data generate --n N --seed S`` writes in one go, ``meta.json`` included.
"""

from __future__ import annotations

from pathlib import Path
import numpy as np

from tensordict import TensorDict

from immnet import keys
from immnet.data.generate import BLOCK
from immnet.data.scratch import publishing
from immnet.data.spec import DataSpec
from immnet.data.storage import (
    META, TENSORS, _allocate, _check_out, _meta, _rows, _write_meta, load_dataset, shard_rows, store_dtypes,
    tensor_files,
)
from immnet.motion import MODE_NAMES, N_MODES
from immnet.progress import progress as progress_bar

_SAME = ("format", "spec_version", "seed", "T", "single_mode", "block", "spec", "dtype")
"""``meta.json`` fields every shard of one whole shares (plus ``shard.count`` and ``shard.n_total``)."""


def _read_shards(dirs) -> list[tuple[Path, dict]]:
    """``[(dir, meta)]`` of the shard directories, each checked by ``load_dataset``, sorted by index."""
    shards = []
    for d in map(Path, dirs):
        if not d.is_dir():
            raise FileNotFoundError(f"shard {d} is not a data set directory")
        _, meta = load_dataset(d)
        if "shard" not in meta:
            raise ValueError(f"{d} is not a shard: its {META} has no 'shard' field "
                             "(made by immnet data generate --shard i/K)")
        shards.append((d, meta))
    if not shards:
        raise ValueError("no shard directories given")
    first_dir, first = shards[0]
    for d, meta in shards[1:]:
        for field in _SAME:
            if meta.get(field) != first.get(field):
                raise ValueError(f"{d} and {first_dir} are not shards of one data set: their {field} differs "
                                 f"({meta.get(field)!r} vs {first.get(field)!r})")
        for field in ("count", "n_total"):
            if meta["shard"][field] != first["shard"][field]:
                raise ValueError(f"{d} and {first_dir} are not shards of one data set: shard {field} "
                                 f"{meta['shard'][field]} vs {first['shard'][field]}")
    if first.get("block") != BLOCK:
        raise ValueError(f"{first_dir} was made in blocks of {first.get('block')} trajectories; "
                         f"this version makes blocks of {BLOCK}")
    return sorted(shards, key=lambda s: (s[1]["shard"]["index"], str(s[0])))


def _check_tiling(shards: list[tuple[Path, dict]]) -> None:
    """Each index ``0..K-1`` once, and rows ``[0, n_total)`` covered exactly once, as the rule says."""
    count, n_total = shards[0][1]["shard"]["count"], shards[0][1]["shard"]["n_total"]
    seen: dict[int, Path] = {}
    for d, meta in shards:
        i = meta["shard"]["index"]
        if i in seen:
            raise ValueError(f"shard {i} of {count} is given twice: {seen[i]} and {d}")
        seen[i] = d
    missing = [i for i in range(count) if i not in seen]
    if missing:
        raise ValueError(f"missing shard(s) {', '.join(map(str, missing))} of {count} "
                         f"(have {', '.join(map(str, sorted(seen)))})")
    stop, prev = 0, None
    for d, meta in sorted(shards, key=lambda s: tuple(s[1]["shard"]["rows"])):
        a, b = meta["shard"]["rows"]
        if a < stop:
            raise ValueError(f"shard {d} (rows [{a}, {b})) overlaps shard {prev} (rows up to {stop})")
        if a > stop:
            raise ValueError(f"no shard holds rows [{stop}, {a}) of {n_total}")
        if b - a != meta["n"]:
            raise ValueError(f"shard {d}: rows [{a}, {b}) but n = {meta['n']}")
        stop, prev = b, d
    if stop != n_total:
        raise ValueError(f"no shard holds rows [{stop}, {n_total}) of {n_total}")
    for d, meta in shards:
        want = list(shard_rows(n_total, meta["shard"]["index"], count))
        if meta["shard"]["rows"] != want:
            raise ValueError(f"shard {d}: rows {meta['shard']['rows']} are not those of shard "
                             f"{meta['shard']['index']} of {count} ({want})")


def merge_shards(out, shard_dirs, overwrite: bool = False, progress: bool = False) -> Path:
    """Join the ``K`` shard directories of one data set into the data set directory ``out``.

    Streams one block of rows per key at a time (memory bounded whatever ``n``); writes into a
    temporary sibling renamed into place only when complete. Errors name what is wrong: a
    directory that is no shard, shards of different seeds or specs, a missing or duplicate
    shard, overlapping rows.
    """
    out = Path(out)
    shards = _read_shards(shard_dirs)
    if any(out.resolve() == d.resolve() for d, _ in shards):
        raise ValueError(f"the output {out} is one of the shards")
    _check_tiling(shards)
    first = shards[0][1]
    n_total, T, block = first["shard"]["n_total"], first["T"], first["block"]
    _check_out(out, overwrite)
    bar = progress_bar(total=n_total, desc=f"merge -> {out.name}", unit="traj", disable=not progress)
    try:
        with publishing(out) as tmp:
            tmp.mkdir()
            dtypes = store_dtypes(DataSpec.from_dict(first["spec"]))
            _allocate(tmp / TENSORS, n_total, T, out, dtypes)
            dst_td = TensorDict.load_memmap(tmp / TENSORS)
            counts = [0] * N_MODES
            for d, meta in shards:  # each checked by load_dataset in _read_shards: its files are read directly
                src_files, _ = tensor_files(d / TENSORS)
                row0, n = meta["shard"]["rows"][0], meta["n"]
                for key, dtype in dtypes.items():
                    dtype = str(dtype).removeprefix("torch.")
                    trail = tuple(dst_td[key].shape[1:])
                    for a in range(0, n, block):
                        m = min(block, n - a)
                        if key not in src_files:  # a shard written before scan times were stored: k dt
                            dt = _rows(src_files[keys.DT][0], np.float32, (), a, m, "r").astype(np.float64)
                            src = np.arange(T, dtype=np.float64) * dt[:, None]
                        else:
                            src = _rows(src_files[key][0], dtype, trail, a, m, "r")
                        dst = _rows(dst_td[key].filename, dtype, trail, row0 + a, m, "r+")
                        dst[:] = src
                        dst.flush()
                        del src, dst
                counts = [c + int(meta["counts_per_mode"][name]) for c, name in zip(counts, MODE_NAMES)]
                bar.update(n)
            del dst_td
            _write_meta(tmp, _meta(first["seed"], n_total, first["spec"], first["single_mode"], counts))
            load_dataset(tmp)  # the merged set passes the same checks as any other
    finally:
        bar.close()
    return out

