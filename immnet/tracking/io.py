"""Tracks as CSV: ``track_id, t, x, y, z`` in (missing values allowed), estimates out.

Rows of many tracks may interleave. Within a track, ``t`` must increase; scans are ``dt`` apart
and a jump of ``k dt`` means ``k - 1`` missed scans (the tracker coasts over them). An empty
``x, y, z`` is a missed detection. Every problem is reported with its line number.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

IN_COLUMNS = ("track_id", "t", "x", "y", "z")
OUT_COLUMNS = (
    "track_id", "t", "x", "vx", "ax", "y", "vy", "ay", "z", "vz", "az", "p_cv", "p_ca", "p_ctp", "p_ctm",
)


def _number(value: str, column: str, line: int, allow_empty: bool) -> float:
    value = value.strip()
    if value == "" or value.lower() == "nan":
        if allow_empty:
            return math.nan
        raise ValueError(f"line {line}: column {column!r} is empty")
    try:
        return float(value)
    except ValueError:
        raise ValueError(f"line {line}: column {column!r} is not a number: {value!r}") from None


def read_tracks_csv(path: str | Path, dt: float):
    """Parse a CSV into ``(ids, z [N, T, 3], rows)``; ``rows`` lists ``(track, step, t)`` per input line."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"input not found: {path}")
    with path.open(newline="") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None:
            raise ValueError(f"{path}: empty file (expected a header {','.join(IN_COLUMNS)})")
        header = [h.strip() for h in header]
        missing = [c for c in IN_COLUMNS if c not in header]
        if missing:
            raise ValueError(f"line 1: missing column(s) {', '.join(missing)} (expected {','.join(IN_COLUMNS)})")
        col = {c: header.index(c) for c in IN_COLUMNS}
        tracks: dict[str, list] = {}
        rows = []
        for line, rec in enumerate(reader, start=2):
            if not rec or all(not v.strip() for v in rec):
                continue
            if len(rec) < len(header):
                raise ValueError(f"line {line}: {len(rec)} fields, expected {len(header)}")
            tid = rec[col["track_id"]].strip()
            if not tid:
                raise ValueError(f"line {line}: column 'track_id' is empty")
            t = _number(rec[col["t"]], "t", line, allow_empty=False)
            xyz = [_number(rec[col[c]], c, line, allow_empty=True) for c in "xyz"]
            seq = tracks.setdefault(tid, [])
            if seq:
                t0, t_last = seq[0][0], seq[-1][0]
                if t <= t_last:
                    raise ValueError(f"line {line}: time {t:g} of track {tid!r} is not after its previous time {t_last:g} (rows of a track must be in time order)")
                k = (t - t0) / dt
                if abs(k - round(k)) > 1e-6:
                    raise ValueError(f"line {line}: time {t:g} of track {tid!r} is not a whole number of scans (dt = {dt:g}) after its start {t0:g}")
            seq.append((t, xyz, line))
            rows.append((tid, t))
    if not tracks:
        raise ValueError(f"{path}: no data rows")
    ids = list(tracks)
    steps = {tid: [round((t - seq[0][0]) / dt) for t, _, _ in seq] for tid, seq in tracks.items()}
    T = max(s[-1] for s in steps.values()) + 1
    z = np.full((len(ids), T, 3), np.nan)
    for i, tid in enumerate(ids):
        for (t, xyz, _), k in zip(tracks[tid], steps[tid]):
            z[i, k] = xyz
    index = {tid: i for i, tid in enumerate(ids)}
    step_of = {(tid, t): k for tid in ids for (t, _, _), k in zip(tracks[tid], steps[tid])}
    return ids, z, [(index[tid], step_of[(tid, t)], tid, t) for tid, t in rows]


def write_tracks_csv(path: str | Path, rows, state: np.ndarray, mode_probs: np.ndarray) -> None:
    """Write one output line per input line, in input order."""
    path = Path(path)
    tmp = path.with_name(path.name + ".partial")
    with tmp.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(OUT_COLUMNS)
        for i, k, tid, t in rows:
            w.writerow([tid, f"{t:g}", *(f"{v:.6f}" for v in state[i, k]), *(f"{p:.6f}" for p in mode_probs[i, k])])
    tmp.replace(path)
