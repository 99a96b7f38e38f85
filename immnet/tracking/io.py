"""Tracks as CSV: ``track_id, t, x, y, z`` or ``track_id, t, range, azimuth, elevation`` in (missing values
allowed), estimates out.

Rows of many tracks may interleave. Within a track, ``t`` must increase and be finite; an empty
``x, y, z`` (or ``nan``) is a missed detection. The file may start with a UTF-8 byte-order mark.
Every problem is reported with its line number.

A radar's plots: ``range`` (slant range, m), ``azimuth`` (degrees clockwise from north, any finite value, taken
modulo 360) and ``elevation`` (degrees above the horizontal, in [-90, 90]) in place of ``x, y, z``, with the radar's
stds given once (``read_tracks_csv(sigmas=...)``, ``immnet track --sigma-range/--sigma-azimuth/--sigma-elevation``) or
per row (``SIGMA_COLUMNS``). Each plot is converted to the radar's east-north-up frame (x east, y north, z up, metres,
origin at the radar) with its covariance (:func:`_converted`), in float64. A Cartesian CSV may give each detection's
covariance (``R_COLUMNS``, m^2). An empty ``range, azimuth, elevation`` is a missed detection. How rows become tracked segments (scans ``dt``
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
POLAR_COLUMNS = ("track_id", "t", "range", "azimuth", "elevation")
"""A radar's plots: slant range (m), azimuth (degrees clockwise from north), elevation (degrees above the horizontal)."""
SIGMA_COLUMNS = ("sigma_range", "sigma_azimuth", "sigma_elevation")
"""The stds of each plot, optional beside ``POLAR_COLUMNS``: m, degrees, degrees."""
R_COLUMNS = ("r_xx", "r_xy", "r_xz", "r_yy", "r_yz", "r_zz")
"""Each detection's covariance, optional beside ``IN_COLUMNS``: the upper triangle of the 3x3 matrix, m^2."""
_R_INDEX = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
SIGMA_OPTIONS = ("--sigma-range", "--sigma-azimuth", "--sigma-elevation")
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
    given, stripped), ``t [R]`` (the same as exact decimals), ``z [R, 3]`` (NaN = missed; a radar's plots converted
    to its east-north-up frame, m) and ``lines [R]`` (line numbers, for messages); ``cov [R, 3, 3]`` each
    detection's covariance (m^2, NaN where missed), None where the file gives none (``track_id, t, x, y, z``);
    ``polar``: the rows were ``range, azimuth, elevation``."""

    ids: list[str]
    times: list[str]
    t: list[Decimal]
    z: np.ndarray
    lines: list[int]
    cov: np.ndarray | None = None
    polar: bool = False

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


def _converted(rho, az, el, s_rho, s_az, s_el) -> tuple[np.ndarray, np.ndarray]:
    """Plots (m, rad, rad) and their stds -> east-north-up ``[..., 3]`` and covariance ``[..., 3, 3]``, float64: the
    unbiased converted measurement (``immnet.data.radar.converted``)."""
    from immnet.data.radar import converted

    return converted(rho, az, el, s_rho, s_az, s_el)


def check_sigmas(sigmas) -> tuple[float, float, float] | None:
    """The radar's stds ``(range m, azimuth deg, elevation deg)`` as given by the options (None: not given); a
    ValueError naming the option unless all three are given, each a finite number > 0."""
    if sigmas is None or all(v is None for v in sigmas):
        return None
    missing = [o for o, v in zip(SIGMA_OPTIONS, sigmas) if v is None]
    if missing:
        raise ValueError(f"the radar's stds are three numbers: give {', '.join(missing)} too "
                         f"(--sigma-range METRES --sigma-azimuth DEG --sigma-elevation DEG)")
    for option, v in zip(SIGMA_OPTIONS, sigmas):
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"{option} is a standard deviation, a finite number > 0; got {v:g}")
    return tuple(float(v) for v in sigmas)


def _layout(header: list[str], sigmas) -> tuple[bool, tuple[str, ...]]:
    """``(polar, extra)``: whether the rows are a radar's plots, and the optional columns read beside the
    positions (``SIGMA_COLUMNS``, ``R_COLUMNS`` or none); a ValueError for a header this module does not read."""
    cart = [c for c in "xyz" if c in header]
    pol = [c for c in POLAR_COLUMNS[2:] if c in header]
    sig = [c for c in SIGMA_COLUMNS if c in header]
    cov = [c for c in R_COLUMNS if c in header]
    if cart and pol:
        raise ValueError(f"line 1: columns {','.join(cart + pol)} mix Cartesian (x,y,z) and polar "
                         f"(range,azimuth,elevation) positions: give one of the two")
    want, extra, other, other_kind = ((POLAR_COLUMNS, sig, cov, "x,y,z rows' covariance") if pol else
                                      (IN_COLUMNS, cov, sig, "range,azimuth,elevation rows' stds"))
    missing = [c for c in want if c not in header]
    if missing:
        raise ValueError(f"line 1: missing column(s) {', '.join(missing)} (expected {','.join(want)})")
    if other:
        raise ValueError(f"line 1: column(s) {','.join(other)} are the {other_kind}, not for "
                         f"{','.join(want[2:])} rows")
    full = SIGMA_COLUMNS if pol else R_COLUMNS
    if extra and len(extra) < len(full):
        raise ValueError(f"line 1: missing column(s) {', '.join(c for c in full if c not in extra)} (the columns "
                         f"{','.join(full)} go together)")
    if pol and extra and sigmas is not None:
        raise ValueError(f"line 1: columns {','.join(SIGMA_COLUMNS)} and the options {', '.join(SIGMA_OPTIONS)} both "
                         f"give the radar's stds: give one of the two")
    if pol and not extra and sigmas is None:
        raise ValueError(f"line 1: range,azimuth,elevation rows need the radar's stds: give {' METRES '.join(SIGMA_OPTIONS[:2])} "
                         f"DEG {SIGMA_OPTIONS[2]} DEG, or the columns {','.join(SIGMA_COLUMNS)}")
    if not pol and sigmas is not None:
        raise ValueError(f"{', '.join(SIGMA_OPTIONS)} are the stds of range,azimuth,elevation rows; this CSV has "
                         f"x,y,z (each row's covariance: the columns {','.join(R_COLUMNS)})")
    return bool(pol), tuple(full if extra else ())


def _plot(rec, col: dict, line: int) -> list[float]:
    """A row's range, azimuth, elevation (m, degrees, degrees; NaN where empty), each checked."""
    rho, az, el = (_number(rec[col[c]], c, line) for c in POLAR_COLUMNS[2:])
    if rho <= 0:
        raise ValueError(f"line {line}: column 'range' is {rho:g}: a slant range is > 0 (m)")
    if math.isinf(az):
        raise ValueError(f"line {line}: column 'azimuth' is {az:g}: an azimuth is a finite number of degrees")
    if not (math.isnan(el) or -90 <= el <= 90):
        raise ValueError(f"line {line}: column 'elevation' is {el:g}: an elevation lies in [-90, 90] degrees")
    return [rho, az, el]


def _stds(rec, col: dict, line: int) -> list[float]:
    """A detection's ``sigma_*`` columns, each a finite number > 0."""
    out = []
    for c in SIGMA_COLUMNS:
        v = _number(rec[col[c]], c, line)
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"line {line}: column {c!r} is {'empty' if math.isnan(v) else f'{v:g}'}: a detection's "
                             f"standard deviation is a finite number > 0")
        out.append(v)
    return out


def _covariance(rec, col: dict, line: int) -> np.ndarray:
    """A detection's ``r_*`` columns as a symmetric 3x3 matrix, positive definite."""
    m = np.empty((3, 3))
    for c, (i, j) in zip(R_COLUMNS, _R_INDEX):
        v = _number(rec[col[c]], c, line)
        if not math.isfinite(v):
            raise ValueError(f"line {line}: column {c!r} is {'empty' if math.isnan(v) else f'{v:g}'}: a detection's "
                             f"covariance entries are finite numbers (m^2)")
        m[i, j] = m[j, i] = v
    try:
        np.linalg.cholesky(m)
    except np.linalg.LinAlgError:
        raise ValueError(f"line {line}: columns {','.join(R_COLUMNS)} are not a positive-definite covariance "
                         f"(eigenvalues {', '.join(f'{e:g}' for e in np.linalg.eigvalsh(m))} m^2)") from None
    return m


def _read_rows(path: Path, reader, ids, times, ts, zs, lines, extras, sigmas=None) -> bool:
    """The rows of ``reader`` (after its header) appended to the lists, each checked (module doc): ``zs`` the
    positions as given (x, y, z or range, azimuth, elevation), ``extras`` each detection's stds or covariance
    (None where missed; nothing appended where the file has neither). Returns whether the rows are plots."""
    last: dict[str, tuple[Decimal, str]] = {}
    header = next(reader, None)
    if header is None:
        raise ValueError(f"{path}: empty file (expected a header {','.join(IN_COLUMNS)})")
    header = [h.strip() for h in header]
    polar, extra = _layout(header, sigmas)
    names = POLAR_COLUMNS if polar else IN_COLUMNS
    col = {c: header.index(c) for c in (*names, *extra)}
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
        xyz = _plot(rec, col, line) if polar else [_number(rec[col[c]], c, line) for c in "xyz"]
        if extra:
            detected = not all(math.isnan(v) for v in xyz)
            extras.append(None if not detected else _stds(rec, col, line) if polar else _covariance(rec, col, line))
        if tid in last and t <= last[tid][0]:
            raise ValueError(f"line {line}: time {text} of track {tid!r} is not after its previous time "
                             f"{last[tid][1]} (rows of a track must be in time order)")
        last[tid] = (t, text)
        ids.append(tid)
        times.append(text)
        ts.append(t)
        zs.append(xyz)
        lines.append(line)
    return polar


def _to_enu(plots: np.ndarray, extras: list, sigmas) -> tuple[np.ndarray, np.ndarray]:
    """Plots ``[R, 3]`` (m, degrees, degrees) and each one's stds (``extras``, or ``sigmas`` for all) -> ENU
    ``[R, 3]`` and covariances ``[R, 3, 3]``, NaN where a plot has an empty field."""
    s = np.full((len(plots), 3), np.nan)
    if sigmas is not None:
        s[:] = sigmas
    else:
        for i, e in enumerate(extras):
            if e is not None:
                s[i] = e
    rad = np.radians
    enu, cov = _converted(plots[:, 0], rad(np.mod(plots[:, 1], 360.0)), rad(plots[:, 2]), s[:, 0], rad(s[:, 1]),
                          rad(s[:, 2]))
    cov[np.isnan(plots).any(-1)] = np.nan
    return enu, cov


def read_tracks_csv(path: str | Path, sigmas=None) -> CsvTracks:
    """Parse and check a tracks CSV (module doc); memory proportional to its rows. ``sigmas``: the radar's stds
    ``(range m, azimuth deg, elevation deg)`` for a CSV of plots without per-row ones (:func:`check_sigmas`)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"input not found: {path}")
    sigmas = check_sigmas(sigmas)
    ids, times, ts, zs, lines, extras = [], [], [], [], [], []
    with path.open(newline="", encoding="utf-8-sig") as f:  # utf-8-sig: a byte-order mark is not a column name
        reader = csv.reader(f)
        try:
            polar = _read_rows(path, reader, ids, times, ts, zs, lines, extras, sigmas)
        except csv.Error as err:  # a field over the csv module's limit, a quote left open at the end
            raise ValueError(f"line {reader.line_num}: not readable as CSV ({err})") from None
    if not ids:
        raise ValueError(f"{path}: no data rows")
    z = np.asarray(zs, dtype=np.float64).reshape(-1, 3)
    cov = None
    if polar:
        z, cov = _to_enu(z, extras, sigmas)
    elif extras:
        cov = np.full((len(ids), 3, 3), np.nan)
        for i, e in enumerate(extras):
            if e is not None:
                cov[i] = e
    return CsvTracks(ids, times, ts, z, lines, cov, polar)


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
