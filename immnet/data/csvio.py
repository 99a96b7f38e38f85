"""Tracks as CSV: ``track_id, t, x, y, z`` or ``track_id, t, range, azimuth, elevation`` in (missing values
allowed), estimates out.

Rows of many tracks may interleave. Within a track, ``t`` must increase and be finite; an empty
``x, y, z`` (or ``nan``) is a missed detection. The file may start with a UTF-8 byte-order mark.
Every problem is reported with its line number.

A radar's plots: ``range`` (slant range, m), ``azimuth`` (degrees clockwise from north, any finite value, taken
modulo 360) and ``elevation`` (degrees above the horizontal, in [-90, 90]) in place of ``x, y, z``, with the radar's
stds given once (``read_tracks_csv(sigmas=...)``, ``immnet track --sigma-range/--sigma-azimuth/--sigma-elevation``) or
per row (``SIGMA_COLUMNS``). Each plot is converted to the radar's east-north-up frame (x east, y north, z up, metres,
origin at the radar) with its covariance (:func:`immnet.data.radar.converted`), in float64. A Cartesian CSV may give
each detection's covariance (``R_COLUMNS``, m^2). An empty ``range, azimuth, elevation`` is a missed detection. How
rows become tracked segments (scans ``dt`` apart, the coasting limit) is ``immnet.tracking.segments``; the output has
one line per input line, in input order, its ``t`` written exactly as the input gave it, and empty fields where there
is no estimate (before a track's first detection, or after it was dropped for coasting too long). After the state and
the mode probabilities come the 21 entries of the position-velocity covariance (``COV_COLUMNS``), empty throughout
for a tracker that keeps no covariance.

A radar's unlabelled plots (:func:`read_plots_csv`, the multi-target tracker's input; docs/multi-target.md): the same
columns without ``track_id``, ``t, range, azimuth, elevation`` or ``t, x, y, z``, the rows of a scan sharing its ``t``
(equal as exact decimals), scans in time order, a row of ``t`` alone a scan without plots; the output has one line
per confirmed track per scan (``PLOT_OUT_COLUMNS``: the state columns, ``updated``, the covariance columns).
"""

from __future__ import annotations

import csv
import functools
import io
import math
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from itertools import combinations_with_replacement, product
from pathlib import Path

import numpy as np

from immnet.data.radar import converted
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


_POSITION, _VELOCITY = ("x", "y", "z"), ("vx", "vy", "vz")
COV_PAIRS = (*combinations_with_replacement(_POSITION, 2), *combinations_with_replacement(_VELOCITY, 2),
             *product(_POSITION, _VELOCITY))
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


def _header(path: Path, reader, sigmas, ids: bool = True, need_stds: bool = True) -> tuple[list, bool, tuple, dict]:
    """``(header, polar, extra, col)`` from a CSV's first row: its names stripped, whether the rows are a radar's
    plots, the optional columns read beside the positions (``SIGMA_COLUMNS``, ``R_COLUMNS`` or none) and the column
    of each name read; a ValueError for an empty file or a header this module does not read. ``ids``: the rows name
    their track (``track_id``); ``need_stds``: plots are converted, so need their stds."""
    header = next(reader, None)
    if header is None:
        want = ','.join(IN_COLUMNS) if ids else f"{','.join(PLOT_COLUMNS)} or {','.join(CART_PLOT_COLUMNS)}"
        raise ValueError(f"{path}: empty file (expected a header {want})")
    header = [h.strip() for h in header]
    cart = [c for c in "xyz" if c in header]
    pol = [c for c in POLAR_COLUMNS[2:] if c in header]
    sig = [c for c in SIGMA_COLUMNS if c in header]
    cov = [c for c in R_COLUMNS if c in header]
    if cart and pol:
        raise ValueError(f"line 1: columns {','.join(cart + pol)} mix Cartesian (x,y,z) and polar "
                         f"(range,azimuth,elevation) positions: give one of the two")
    want, extra, other, other_kind = ((POLAR_COLUMNS, sig, cov, "x,y,z rows' covariance") if pol else
                                      (IN_COLUMNS, cov, sig, "range,azimuth,elevation rows' stds"))
    want = want if ids else want[1:]
    missing = [c for c in want if c not in header]
    if missing:
        raise ValueError(f"line 1: missing column(s) {', '.join(missing)} (expected {','.join(want)})")
    if other:
        raise ValueError(f"line 1: column(s) {','.join(other)} are the {other_kind}, not for "
                         f"{','.join(want[-3:])} rows")
    full = SIGMA_COLUMNS if pol else R_COLUMNS
    if extra and len(extra) < len(full):
        raise ValueError(f"line 1: missing column(s) {', '.join(c for c in full if c not in extra)} (the columns "
                         f"{','.join(full)} go together)")
    if pol and extra and sigmas is not None:
        raise ValueError(f"line 1: columns {','.join(SIGMA_COLUMNS)} and the options {', '.join(SIGMA_OPTIONS)} both "
                         f"give the radar's stds: give one of the two")
    if pol and not extra and sigmas is None and need_stds:
        raise ValueError(f"line 1: range,azimuth,elevation rows need the radar's stds: give {' METRES '.join(SIGMA_OPTIONS[:2])} "
                         f"DEG {SIGMA_OPTIONS[2]} DEG, or the columns {','.join(SIGMA_COLUMNS)}")
    if not pol and sigmas is not None:
        raise ValueError(f"{', '.join(SIGMA_OPTIONS)} are the stds of range,azimuth,elevation rows; this CSV has "
                         f"x,y,z (each row's covariance: the columns {','.join(R_COLUMNS)})")
    extra = full if extra else ()
    return header, bool(pol), extra, {c: header.index(c) for c in (*want, *extra)}


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


def _detection_field(rec, col: dict, c: str, line: int, std: bool) -> float:
    """A detection's column ``c`` (``SIGMA_COLUMNS``, ``R_COLUMNS``): a finite number, > 0 where it is a ``std``."""
    v = _number(rec[col[c]], c, line)
    if not (math.isfinite(v) and (v > 0 or not std)):
        what = "standard deviation is a finite number > 0" if std else "covariance entries are finite numbers (m^2)"
        raise ValueError(f"line {line}: column {c!r} is {'empty' if math.isnan(v) else f'{v:g}'}: a detection's {what}")
    return v


def _stds(rec, col: dict, line: int) -> list[float]:
    """A detection's ``sigma_*`` columns, each a finite number > 0."""
    return [_detection_field(rec, col, c, line, std=True) for c in SIGMA_COLUMNS]


def _covariance(rec, col: dict, line: int) -> np.ndarray:
    """A detection's ``r_*`` columns as a symmetric 3x3 matrix, positive definite."""
    m = np.empty((3, 3))
    for c, (i, j) in zip(R_COLUMNS, _R_INDEX):
        m[i, j] = m[j, i] = _detection_field(rec, col, c, line, std=False)
    try:
        np.linalg.cholesky(m)
    except np.linalg.LinAlgError:
        raise ValueError(f"line {line}: columns {','.join(R_COLUMNS)} are not a positive-definite covariance "
                         f"(eigenvalues {', '.join(f'{e:g}' for e in np.linalg.eigvalsh(m))} m^2)") from None
    return m


def _data_rows(reader, header: list[str], col: dict, polar: bool, exact: bool):
    """``(line, rec, t text, t, position)`` of each row of ``reader`` after its header that is not blank: its fields
    counted (as many as the header, or with ``exact`` False at least as many), its ``track_id`` (where the file has
    one) not empty, its ``t`` read (the text stripped, and as an exact decimal) and its position (a plot's range,
    azimuth, elevation, or its x, y, z) read, each checked; a ValueError names the line."""
    for line, rec in enumerate(reader, start=2):
        if not rec or all(not v.strip() for v in rec):
            continue
        if len(rec) < len(header) or exact and len(rec) > len(header):
            raise ValueError(f"line {line}: {len(rec)} fields, but the header has {len(header)} ({','.join(header)})")
        if "track_id" in col and not rec[col["track_id"]].strip():
            raise ValueError(f"line {line}: column 'track_id' is empty: in a CSV with a track_id column every row "
                             f"names its track (unlabelled plots, for the multi-target tracker, have no such column)")
        text = rec[col["t"]].strip()
        t = _time(text, line)
        yield line, rec, text, t, _plot(rec, col, line) if polar else [_number(rec[col[c]], c, line) for c in "xyz"]


def _read_rows(path: Path, reader, sigmas) -> CsvTracks:
    """The rows of ``reader`` after its header, each checked (module doc): ``rows`` each row's track, ``t`` text,
    ``t``, position as given (x, y, z or range, azimuth, elevation) and line, ``extras`` each detection's stds or
    covariance (None where missed; nothing appended where the file has neither)."""
    rows, extras = [], []
    last: dict[str, tuple[Decimal, str]] = {}
    header, polar, extra, col = _header(path, reader, sigmas)
    for line, rec, text, t, xyz in _data_rows(reader, header, col, polar, exact=False):
        tid = rec[col["track_id"]].strip()
        if extra:
            detected = not all(math.isnan(v) for v in xyz)
            extras.append(None if not detected else _stds(rec, col, line) if polar else _covariance(rec, col, line))
        if tid in last and t <= last[tid][0]:
            raise ValueError(f"line {line}: time {text} of track {tid!r} is not after its previous time "
                             f"{last[tid][1]} (rows of a track must be in time order)")
        last[tid] = (t, text)
        rows.append((tid, text, t, xyz, line))
    if not rows:
        raise ValueError(f"{path}: no data rows")
    ids, times, ts, zs, lines = map(list, zip(*rows))
    z, cov = _enu(np.asarray(zs, dtype=np.float64).reshape(-1, 3), extras, polar, extra, sigmas)
    return CsvTracks(ids, times, ts, z, lines, cov, polar)


def _enu(given: np.ndarray, extras: list, polar: bool, extra: tuple, sigmas) -> tuple[np.ndarray, np.ndarray | None]:
    """Positions ``[R, 3]`` as the file gives them -> east-north-up and each one's covariance: ``x, y, z`` as they are
    with their ``R_COLUMNS`` covariance (NaN where an entry of ``extras`` is None), None where the file gives none; a
    radar's plots (m, degrees, degrees) with each one's stds (``extras``, or ``sigmas`` for all) as the unbiased
    converted measurement (``immnet.data.radar.converted``), NaN where a plot has an empty field."""
    if not polar:
        return given, _filled(extras, (3, 3)) if extra else None
    s = _filled(extras, (3,)) if sigmas is None else np.broadcast_to(np.asarray(sigmas, np.float64), given.shape)
    rad = np.radians
    enu, cov = converted(given[:, 0], rad(np.mod(given[:, 1], 360.0)), rad(given[:, 2]), s[:, 0], rad(s[:, 1]),
                         rad(s[:, 2]))
    cov[np.isnan(given).any(-1)] = np.nan
    return enu, cov


def _filled(extras: list, trail: tuple) -> np.ndarray:
    """``extras`` as one array ``[R, *trail]``, NaN rows where an entry is None (a missed detection)."""
    out = np.full((len(extras), *trail), np.nan)
    for i, e in enumerate(extras):
        if e is not None:
            out[i] = e
    return out


def _parsed(path: str | Path, sigmas, parse):
    """``parse(path, reader, sigmas)``: the rows of the CSV file ``path`` read and checked (``sigmas`` checked first,
    :func:`check_sigmas`); a FileNotFoundError where there is no file, a ValueError naming the line of a row the csv
    module cannot read."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"input not found: {path}")
    sigmas = check_sigmas(sigmas)
    with path.open(newline="", encoding="utf-8-sig") as f:  # utf-8-sig: a byte-order mark is not a column name
        reader = csv.reader(f)
        try:
            return parse(path, reader, sigmas)
        except csv.Error as err:  # a field over the csv module's limit, a quote left open at the end
            raise ValueError(f"line {reader.line_num}: not readable as CSV ({err})") from None


def read_tracks_csv(path: str | Path, sigmas=None) -> CsvTracks:
    """Parse and check a tracks CSV (module doc); memory proportional to its rows. ``sigmas``: the radar's stds
    ``(range m, azimuth deg, elevation deg)`` for a CSV of plots without per-row ones (:func:`check_sigmas`)."""
    return _parsed(path, sigmas, _read_rows)


PLOT_COLUMNS = ("t", "range", "azimuth", "elevation")
"""A radar's unlabelled plots (no ``track_id``): the multi-target tracker's input, as ``immnet data scenes`` writes it."""
CART_PLOT_COLUMNS = ("t", "x", "y", "z")
"""Unlabelled plots in east-north-up coordinates (m)."""
PLOT_OUT_COLUMNS = STATE_COLUMNS + ("updated",) + COV_COLUMNS
"""The multi-target output: a confirmed track at a scan, ``updated`` 1 where a plot updated it there, else 0."""


@dataclass
class CsvPlots:
    """The scans of a plots CSV (no ``track_id``), in file order. Per scan: ``times [S]`` (its ``t`` text as its
    first row gives it, stripped), ``t [S]`` (the same as exact decimals), ``scan_lines [S]`` (its first line),
    ``offsets [S + 1]`` (scan ``k``'s plots are rows ``offsets[k]:offsets[k + 1]``). Per plot: ``given [P, 3]`` (as
    the file gives it: ``x, y, z`` m, or ``range`` m, ``azimuth``, ``elevation`` degrees), ``lines [P]``, ``z [P, 3]``
    (east-north-up, m; None where the plots were read without converting them) and ``cov [P, 3, 3]`` (m^2; None for
    ``x, y, z`` without ``R_COLUMNS``); ``polar``: the plots were ``range, azimuth, elevation``."""

    times: list[str]
    t: list[Decimal]
    scan_lines: list[int]
    offsets: np.ndarray
    given: np.ndarray
    lines: np.ndarray
    z: np.ndarray | None = None
    cov: np.ndarray | None = None
    polar: bool = False

    def __len__(self) -> int:
        return len(self.times)


def csv_header(path: str | Path) -> list[str] | None:
    """A CSV's first row, each name stripped (a byte-order mark dropped); None for an empty file."""
    with Path(path).open(newline="", encoding="utf-8-sig") as f:
        try:
            header = next(csv.reader(f), None)
        except csv.Error as err:
            raise ValueError(f"line 1: not readable as CSV ({err})") from None
    return None if header is None else [h.strip() for h in header]


def _read_plot_rows(path: Path, reader, sigmas, convert: bool) -> CsvPlots:
    """The scans of ``reader``'s rows after its header, each row checked (``read_plots_csv``)."""
    header, polar, extra, col = _header(path, reader, sigmas, ids=False, need_stds=convert)
    pos = PLOT_COLUMNS[1:] if polar else CART_PLOT_COLUMNS[1:]
    times, ts, scan_lines, offsets, given, lines, extras = [], [], [], [], [], [], []
    empty_line = None  # the line of the current scan's empty row (a scan without plots), if any
    for line, rec, text, t, xyz in _data_rows(reader, header, col, polar, exact=True):
        empty = [repr(c) for c, v in zip(pos, xyz) if math.isnan(v)]
        if 0 < len(empty) < 3:
            raise ValueError(f"line {line}: column{'s' if len(empty) > 1 else ''} {', '.join(empty)} "
                             f"{'are' if len(empty) > 1 else 'is'} empty in a plot: a plot gives {','.join(pos)}, all "
                             f"three (a scan without plots leaves all three empty)")
        if not ts or t != ts[-1]:  # a new scan
            if ts and t < ts[-1]:
                raise ValueError(f"line {line}: time {text} is before the previous scan's time {times[-1]} (line "
                                 f"{scan_lines[-1]}): scans come in time order, the plots of a scan together under "
                                 f"its t")
            if ts and float(t) <= float(ts[-1]):
                raise ValueError(f"line {line}: time {text} and the previous scan's time {times[-1]} are one number in "
                                 f"float64: give the plots of one scan one t")
            offsets.append(len(given))
            times.append(text)
            ts.append(t)
            scan_lines.append(line)
            empty_line = None
        has_plots = len(given) > offsets[-1]
        if empty and has_plots or not empty and empty_line is not None:
            first = lines[offsets[-1]] if has_plots else line
            raise ValueError(f"line {line}: the scan at time {times[-1]} has a plot (line {first}) and an empty row "
                             f"(line {line if empty else empty_line}: a scan without plots): give one or the other")
        if empty:
            empty_line = line
            continue
        if extra:
            extras.append(_stds(rec, col, line) if polar else _covariance(rec, col, line))
        given.append(xyz)
        lines.append(line)
    if not ts:
        raise ValueError(f"{path}: no data rows")
    offsets.append(len(given))
    given = np.asarray(given, dtype=np.float64).reshape(-1, 3)
    z, cov = _enu(given, extras, polar, extra, sigmas) if convert or not polar else (None, None)
    return CsvPlots(times, ts, scan_lines, np.asarray(offsets, np.int64), given, np.asarray(lines, np.int64), z, cov,
                    polar)


def read_plots_csv(path: str | Path, sigmas=None, convert: bool = True) -> CsvPlots:
    """Parse and check a CSV of unlabelled plots, ``t, range, azimuth, elevation`` or ``t, x, y, z`` (no
    ``track_id``; optional columns as for ``read_tracks_csv``: ``SIGMA_COLUMNS`` beside polar plots, ``R_COLUMNS``
    beside Cartesian ones), into scans: the rows of one scan share its ``t`` (equal as exact decimals), scans come in
    time order, and a row of ``t`` alone (the positions empty) is a scan without plots. Polar plots are converted to
    east-north-up with their covariance (``sigmas`` or the ``sigma_*`` columns, as ``read_tracks_csv``); with
    ``convert=False`` they are only read and checked (no stds needed). Every problem is a ValueError naming its
    line."""
    return _parsed(path, sigmas, functools.partial(_read_plot_rows, convert=convert))


def plot_track_rows(time: str, ids, state: np.ndarray, mode_probs: np.ndarray | None, updated,
                    state_cov: np.ndarray) -> list[str]:
    """The ``PLOT_OUT_COLUMNS`` lines of a scan's confirmed tracks: ``ids [K]``, ``state [K, 9]``, ``mode_probs
    [K, 4]`` (None: empty fields), ``updated [K]`` (written 1/0), ``state_cov [K, 9, 9]``."""
    probs = np.full((len(ids), 4), np.nan) if mode_probs is None else mode_probs
    fields = zip(_fields(np.concatenate([state, probs], 1), STATE_FORMAT), _fields(cov_columns(state_cov), COV_FORMAT))
    at = _quoted([time])[time]
    return [f"{int(i)},{at},{a},{int(bool(u))},{b}\r\n" for i, u, (a, b) in zip(ids, updated, fields)]


STATE_FORMAT = ",".join(["%.6f"] * 13)
"""The fields of the state and the mode probabilities: six decimals."""
COV_FORMAT = ",".join(["%.9g"] * len(COV_COLUMNS))
"""The covariance fields: 9 significant digits, a float32 exactly."""


def _fields(numbers: np.ndarray, fmt: str) -> list[str]:
    """Each row of ``numbers [R, C]`` as its CSV fields by ``fmt`` (a %-format per column), NaN an empty field (no
    number these formats write contains "nan" otherwise)."""
    return [(fmt % tuple(row)).replace("nan", "") for row in numbers.tolist()]


def _quoted(values) -> dict[str, str]:
    """Each distinct string of ``values`` as the csv module writes it as a field (quoted where it must be)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    out: dict[str, str] = {}
    for v in values:
        if v not in out:
            buf.seek(0)
            buf.truncate()
            w.writerow([v, ""])
            out[v] = buf.getvalue()[:-2]  # the field, without the empty one's comma and the line's end
    return out


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
    ids, times = _quoted(tracks.ids), _quoted(tracks.times)
    fields = zip(tracks.ids, tracks.times, _fields(np.concatenate([state, mode_probs], 1), STATE_FORMAT),
                 _fields(cov, COV_FORMAT))
    with publishing(path) as tmp, tmp.open("x", newline="") as f:  # "x": never onto an existing file
        csv.writer(f).writerow(OUT_COLUMNS)
        f.write("".join(f"{ids[i]},{times[t]},{a},{b}\r\n" for i, t, a, b in fields))
