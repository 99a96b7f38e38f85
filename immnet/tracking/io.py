"""Tracks as CSV: ``track_id, t, x, y, z`` in (missing values allowed), estimates out.

Rows of many tracks may interleave. Within a track, ``t`` must increase and be finite; an empty
``x, y, z`` (or ``nan``) is a missed detection. The file may start with a UTF-8 byte-order mark.
Every problem is reported with its line number. How rows become tracked segments (scans ``dt``
apart, the coasting limit) is ``immnet.tracking.segments``; the output has one line per input line,
in input order, its ``t`` written exactly as the input gave it, and empty fields where there is no
estimate (before a track's first detection, or after it was dropped for coasting too long). After the state
and the mode probabilities come the 21 entries of the position-velocity covariance (``COV_COLUMNS``), empty
throughout for a tracker that keeps no covariance.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from immnet.data.scratch import publishing

IN_COLUMNS = ("track_id", "t", "x", "y", "z")
STATE_COLUMNS = (
    "track_id", "t", "x", "vx", "ax", "y", "vy", "ay", "z", "vz", "az", "p_cv", "p_ca", "p_ctp", "p_ctm",
)
_NAMES = {"x": 0, "y": 3, "z": 6, "vx": 1, "vy": 4, "vz": 7}  # a name's index in the state [x, vx, ax, y, vy, ay, z, vz, az]


def _pairs(rows: str, cols: str, upper: bool) -> tuple:
    names_r, names_c = rows.split(), cols.split()
    return tuple((a, b) for i, a in enumerate(names_r) for j, b in enumerate(names_c) if not upper or j >= i)


COV_PAIRS = (
    _pairs("x y z", "x y z", True) + _pairs("vx vy vz", "vx vy vz", True) + _pairs("x y z", "vx vy vz", False)
)
"""The covariance entries written: the position block's upper triangle (m^2), the velocity block's (m^2/s^2),
then the whole position-velocity block (m^2/s), row-major: 21 entries, the 6x6 position-velocity covariance."""
COV_COLUMNS = tuple(f"cov_{a}{b}" for a, b in COV_PAIRS)  # cov_xx, cov_xy, ..., cov_vzvz, cov_xvx, ..., cov_zvz
COV_INDEX = tuple((_NAMES[a], _NAMES[b]) for a, b in COV_PAIRS)
"""Each covariance column's entry ``(i, j)`` of the state covariance ``[9, 9]``."""
OUT_COLUMNS = STATE_COLUMNS + COV_COLUMNS


@dataclass
class CsvTracks:
    """The rows of a tracks CSV, in file order: ``ids [R]`` (track), ``times [R]`` (the ``t`` text as
    given, stripped), ``t [R]`` (the same as exact decimals), ``z [R, 3]`` (NaN = missed) and
    ``lines [R]`` (line numbers, for messages)."""

    ids: list[str]
    times: list[str]
    t: list[Decimal]
    z: np.ndarray
    lines: list[int]

    def __len__(self) -> int:
        return len(self.ids)


def _number(value: str, column: str, line: int) -> float:
    value = value.strip()
    if value == "" or value.lower() == "nan":
        return math.nan
    try:
        return float(value)
    except ValueError:
        raise ValueError(f"line {line}: column {column!r} is not a number: {value!r}") from None


def _time(value: str, line: int) -> Decimal:
    if value == "":
        raise ValueError(f"line {line}: column 't' is empty")
    try:
        t = Decimal(value)
    except InvalidOperation:
        raise ValueError(f"line {line}: column 't' is not a number: {value!r}") from None
    if not t.is_finite():
        raise ValueError(f"line {line}: column 't' is not a finite time: {value!r}")
    return t


def _read_rows(path: Path, reader, ids, times, ts, zs, lines) -> None:
    """The rows of ``reader`` (after its header) appended to the lists, each checked (module doc)."""
    last: dict[str, tuple[Decimal, str]] = {}
    header = next(reader, None)
    if header is None:
        raise ValueError(f"{path}: empty file (expected a header {','.join(IN_COLUMNS)})")
    header = [h.strip() for h in header]
    missing = [c for c in IN_COLUMNS if c not in header]
    if missing:
        raise ValueError(f"line 1: missing column(s) {', '.join(missing)} (expected {','.join(IN_COLUMNS)})")
    col = {c: header.index(c) for c in IN_COLUMNS}
    for line, rec in enumerate(reader, start=2):
        if not rec or all(not v.strip() for v in rec):
            continue
        if len(rec) < len(header):
            raise ValueError(f"line {line}: {len(rec)} fields, expected {len(header)}")
        tid = rec[col["track_id"]].strip()
        if not tid:
            raise ValueError(f"line {line}: column 'track_id' is empty")
        text = rec[col["t"]].strip()
        t = _time(text, line)
        xyz = [_number(rec[col[c]], c, line) for c in "xyz"]
        if tid in last and t <= last[tid][0]:
            raise ValueError(f"line {line}: time {text} of track {tid!r} is not after its previous time "
                             f"{last[tid][1]} (rows of a track must be in time order)")
        last[tid] = (t, text)
        ids.append(tid)
        times.append(text)
        ts.append(t)
        zs.append(xyz)
        lines.append(line)


def read_tracks_csv(path: str | Path) -> CsvTracks:
    """Parse and check a tracks CSV (module doc); memory proportional to its rows."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"input not found: {path}")
    ids, times, ts, zs, lines = [], [], [], [], []
    with path.open(newline="", encoding="utf-8-sig") as f:  # utf-8-sig: a byte-order mark is not a column name
        reader = csv.reader(f)
        try:
            _read_rows(path, reader, ids, times, ts, zs, lines)
        except csv.Error as err:  # a field over the csv module's limit, a quote left open at the end
            raise ValueError(f"line {reader.line_num}: not readable as CSV ({err})") from None
    if not ids:
        raise ValueError(f"{path}: no data rows")
    return CsvTracks(ids, times, ts, np.asarray(zs, dtype=np.float64).reshape(-1, 3), lines)


def _field(v: float) -> str:
    return "" if math.isnan(v) else f"{v:.6f}"


def _cov_field(v: float) -> str:
    return "" if math.isnan(v) else f"{v:.9g}"  # 9 significant digits: a float32 exactly


def cov_columns(state_cov: np.ndarray) -> np.ndarray:
    """The ``COV_COLUMNS`` entries ``[..., 21]`` of state covariances ``[..., 9, 9]``."""
    rows, cols = zip(*COV_INDEX)
    return state_cov[..., list(rows), list(cols)]


def write_tracks_csv(path: str | Path, tracks: CsvTracks, state: np.ndarray, mode_probs: np.ndarray,
                     state_cov: np.ndarray | None = None) -> None:
    """One output line per input row (``state [R, 9]``, ``mode_probs [R, 4]``, the covariance columns of
    ``state_cov [R, 9, 9]``, empty throughout where None; NaN -> an empty field), written to a temporary sibling
    of ``path`` and moved onto it only when complete (``immnet.data.scratch``)."""
    cov = np.full((len(tracks), len(COV_COLUMNS)), np.nan) if state_cov is None else cov_columns(state_cov)
    with publishing(path) as tmp, tmp.open("x", newline="") as f:  # "x": never onto an existing file
        w = csv.writer(f)
        w.writerow(OUT_COLUMNS)
        for r in range(len(tracks)):
            w.writerow([tracks.ids[r], tracks.times[r], *map(_field, state[r]), *map(_field, mode_probs[r]),
                        *map(_cov_field, cov[r])])
