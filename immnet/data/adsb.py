"""Real ADS-B flights: read a sample file, clean it and cut it into flights (docs/real-data.md, "Real flights").

A sample is a file of ADS-B state vectors, one record per aircraft and time: ``timestamp``
(epoch, ms or s, or an ISO 8601 string), ``icao24`` (the transponder's address), ``latitude``,
``longitude`` (degrees), ``altitude`` (barometric, feet) and optionally ``onground`` and
``last_position`` (the time of the position message). The ``traffic`` package ships such samples in
its wheel as JSON; they are read as data (``json``), the package itself is never imported. A CSV file
(``.csv[.gz]``, a header row) holds the same fields; OpenSky's own names are read too (``FIELDS``: its
historical state vectors' ``time``, ``lat``, ``lon``, ``baroaltitude`` in metres, ``lastposupdate``, and its
REST API's ``time_position``, ``baro_altitude``, ``on_ground``), so that a recording of one's own reads as it is.
The velocity an aircraft reports of itself (``groundspeed``, ``track``, ``vertical_rate``; optional, kept in
:class:`Records` in SI units and read by nothing that builds a data set) is in knots and feet per minute under
traffic's names, in m/s under OpenSky's (``velocity``, ``heading`` / ``true_track``, ``vertrate`` /
``vertical_rate``): a file's velocity has its altitude's units (``METRES``).

Cleaning, per aircraft in time order (each step counted in :class:`Flights`' ``counts``):

1. on-ground rows are dropped (``onground``), so are airborne rows with a null required field (``incomplete``);
2. **fresh positions only**: ADS-B state vectors repeat the last decoded position until the next
   position message, so a row is kept only where ``(latitude, longitude)`` differs from the previous
   row's (``stale``). A position is timed by ``last_position`` where the record has it, else by
   ``timestamp``; a position not later than the previous kept one is dropped (``duplicate_time``);
3. **glitches**: a point is dropped (``glitch``) when, from the previous kept point ``dt`` seconds
   before, it implies a horizontal distance beyond ``max_speed (dt + time_slack)`` or an altitude change
   beyond ``max_climb (dt + time_slack)`` (``time_slack`` covers positions timed to whole seconds). After
   ``MAX_STREAK`` glitches in a row the previous point is the doubtful one: the track restarts there;
4. **flights**: a gap of more than ``max_gap`` seconds between kept points (or a restart) starts a new
   flight; flights of fewer than ``min_points`` points are dropped (``short``).

Altitudes are barometric (pressure altitude, ISA), converted from feet to metres and used as the height
above the ellipsoid: the difference is a slowly varying offset that a simulated radar's truth does not
need to know.
"""

from __future__ import annotations

import csv
import gzip
import hashlib
import importlib.util
import json
import math
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from immnet.data.geodesy import geodetic_to_ecef, local_step

FEET = 0.3048
"""Metres per foot."""
REQUIRED = ("timestamp", "icao24", "latitude", "longitude", "altitude")
FIELDS = {
    "timestamp": ("timestamp", "time"),
    "icao24": ("icao24",),
    "latitude": ("latitude", "lat"),
    "longitude": ("longitude", "lon"),
    "altitude": ("altitude", "baroaltitude", "baro_altitude"),
    "onground": ("onground", "on_ground"),
    "last_position": ("last_position", "lastposupdate", "time_position"),
    "groundspeed": ("groundspeed", "velocity"),
    "track": ("track", "heading", "true_track"),
    "vertical_rate": ("vertical_rate", "vertrate"),
}
"""Each field and the names a file may give it, the first present read: traffic's, then OpenSky's (historical state
vectors, then the REST API's)."""
METRES = ("baroaltitude", "baro_altitude")
"""The altitude names whose values are metres (OpenSky's), and the file's velocity m/s; ``altitude`` is in feet
(traffic's), and the file's ground speed in knots, its vertical rate in feet per minute."""
KNOT = 1852.0 / 3600.0
"""Metres per second per knot."""
SUFFIXES = (".json.gz", ".json", ".jsonl.gz", ".jsonl")
CSV_SUFFIXES = (".csv", ".csv.gz")
MAX_STREAK = 5
"""Glitches in a row after which a track restarts at the next point."""
MS_EPOCH = 1e11
"""A numeric timestamp above this is in milliseconds (1e11 s is the year 5138; 1e11 ms is 1973)."""


# --- finding a sample --------------------------------------------------------------------------
def samples_dir() -> Path | None:
    """``<traffic>/data/samples`` of an installed ``traffic`` package (found, not imported), or None."""
    try:
        spec = importlib.util.find_spec("traffic")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    for loc in spec.submodule_search_locations:
        d = Path(loc) / "data" / "samples"
        if d.is_dir():
            return d
    return None


def available_samples(root: Path | None = None) -> list[str]:
    """The sample names under ``root`` (default :func:`samples_dir`): paths without their suffix."""
    root = samples_dir() if root is None else Path(root)
    if root is None:
        return []
    return sorted(p.relative_to(root).as_posix()[: -len(suf)] for p in root.rglob("*") for suf in SUFFIXES
                  if p.is_file() and p.name.endswith(suf))


def resolve_sample(name) -> Path:
    """A file path as given, or a sample name such as ``collections/quickstart`` -> its file."""
    p = Path(name)
    if p.is_file():
        return p
    root = samples_dir()
    if root is not None and ".." not in p.parts and not p.is_absolute():
        for suf in SUFFIXES:
            candidate = root / f"{p.as_posix()}{suf}"
            if candidate.is_file():
                return candidate
    if root is None:
        hint = ("no sample directory: traffic's sample files are not installed "
                "(pip install --no-deps 'traffic==2.13', or pip install 'immnet[real]')")
    else:
        hint = f"available samples in {root}: {', '.join(available_samples(root))}"
    raise FileNotFoundError(f"no ADS-B sample {str(name)!r}: neither a file nor a sample name; {hint}")


def file_digest(path) -> str:
    """The SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


# --- reading ------------------------------------------------------------------------------------
_UNREADABLE = (OSError, EOFError, UnicodeDecodeError, gzip.BadGzipFile)
"""What reading a sample file can raise that means it cannot be read (refused by name as a ValueError)."""


def _open_text(path: Path, **kwargs):
    """``path`` opened as text, gzip decompressed where it is gzip, whatever its name (its first two bytes)."""
    with open(path, "rb") as f:
        zipped = f.read(2) == b"\x1f\x8b"
    return (gzip.open if zipped else open)(path, "rt", **kwargs)


def _load_json(path: Path):
    """The JSON value of a file (gzip decompressed, whatever its name; ``.jsonl``: a list of its lines' values)."""
    try:
        with _open_text(path, encoding="utf-8") as f:
            if ".jsonl" in path.name:
                out = []
                for i, line in enumerate(f, 1):
                    if line.strip():
                        try:
                            out.append(json.loads(line))
                        except json.JSONDecodeError as err:
                            raise ValueError(f"{path}: line {i} is not valid JSON ({err})") from None
                return out
            return json.load(f)
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from None
    except _UNREADABLE as err:
        raise ValueError(f"{path}: cannot be read ({type(err).__name__}: {err})") from None


def _csv_value(text: str):
    """A CSV cell as JSON would hold it: empty -> None, a number -> float, true/false -> bool, else the text."""
    text = text.strip()
    if not text:
        return None
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    try:
        return float(text)
    except ValueError:
        return text


def _load_csv(path: Path) -> list[dict]:
    """The rows of a CSV file with a header (gzip decompressed, whatever its name) as records; ``icao24`` kept as
    text (an address such as ``400123`` is no number)."""
    try:
        with _open_text(path, encoding="utf-8-sig", newline="") as f:  # a spreadsheet's BOM dropped
            reader = csv.DictReader(f)
            if not reader.fieldnames:
                raise ValueError(f"{path}: an empty CSV file (no header row)")
            out = []
            for i, row in enumerate(reader):
                if None in row:  # more cells than the header names
                    raise ValueError(f"{path}: data row {i + 1} has {len(reader.fieldnames) + len(row[None])} cells, "
                                     f"the header {len(reader.fieldnames)}")
                out.append({k: None if v is None else (v.strip() or None) if k == "icao24" else _csv_value(v)
                            for k, v in row.items()})
            return out
    except (*_UNREADABLE, csv.Error) as err:
        raise ValueError(f"{path}: cannot be read ({type(err).__name__}: {err})") from None


def _names(present, path: Path) -> dict[str, str]:
    """Each field of ``FIELDS`` -> the name the file gives it (the first of its names among ``present``); a ValueError
    for a required field under none of its names."""
    present = set(present)
    names = {k: next((a for a in aliases if a in present), k) for k, aliases in FIELDS.items()}
    missing = [k for k in REQUIRED if names[k] not in present]
    if missing:
        raise ValueError(f"{path}: no field {' or '.join(map(repr, FIELDS[missing[0]]))} (has {sorted(present)[:20]}; "
                         f"required: {', '.join(REQUIRED)}, under traffic's or OpenSky's names)")
    return names


def _columns(value, path: Path) -> tuple[dict[str, list], dict[str, str]]:
    """Columns of the records by ``FIELDS``' names, and the name each had in the file: a list of objects, or pandas'
    ``columns`` orientation ``{field: {row: v}}``."""
    if isinstance(value, list):
        for i, r in enumerate(value):
            if not isinstance(r, dict):
                raise ValueError(f"{path}: record {i} is a {type(r).__name__}, not an object of fields")
        names = _names(value[0] if value else REQUIRED, path)
        cols = {}
        for k, name in names.items():
            try:
                cols[k] = [r[name] for r in value]
            except KeyError:
                if k in REQUIRED:
                    i = next(i for i, r in enumerate(value) if name not in r)
                    raise ValueError(f"{path}: record {i} lacks the required field {name!r} (has {sorted(value[i])}; "
                                     f"required: {', '.join(REQUIRED)})") from None
                cols[k] = [r.get(name) for r in value]
        return cols, names
    if isinstance(value, dict) and value and all(isinstance(v, (dict, list)) for v in value.values()):
        names = _names(value, path)
        first = value[names[REQUIRED[0]]]
        index = list(first) if isinstance(first, dict) else None
        n = len(first)
        cols = {}
        for k, name in names.items():
            if name not in value:
                cols[k] = [None] * n
                continue
            c = value[name]
            try:
                cols[k] = [c[i] for i in index] if index is not None else list(c)
            except (KeyError, TypeError):
                raise ValueError(f"{path}: column {name!r} does not have the rows of column "
                                 f"{names[REQUIRED[0]]!r}") from None
            if len(cols[k]) != n:
                raise ValueError(f"{path}: column {name!r} has {len(cols[k])} rows, {names[REQUIRED[0]]!r} has {n}")
        return cols, names
    raise ValueError(f"{path}: expected a JSON list of records (or an object of columns), got a "
                     f"{type(value).__name__}{' with fields ' + str(sorted(value)[:8]) if isinstance(value, dict) else ''}")


def _floats(col: list, name: str, path: Path) -> np.ndarray:
    try:
        a = np.array(col, dtype=np.float64)  # None -> NaN (a null value: the row is incomplete)
    except (TypeError, ValueError):
        i = next(i for i, v in enumerate(col) if v is not None and not isinstance(v, (int, float)))
        raise ValueError(f"{path}: record {i} has {name} = {col[i]!r}, not a number") from None
    if a.ndim != 1:
        raise ValueError(f"{path}: field {name!r} holds lists, not numbers")
    return a


def _times(col: list, name: str, path: Path) -> np.ndarray:
    """Epoch seconds from numbers (ms above ``MS_EPOCH``, else s) or ISO 8601 strings (UTC if naive)."""
    if str not in set(map(type, col)):
        a = _floats(col, name, path)
        return np.where(np.abs(a) > MS_EPOCH, a / 1000.0, a)
    out = np.empty(len(col))
    for i, v in enumerate(col):
        if v is None:
            out[i] = np.nan
        elif isinstance(v, str):
            try:
                d = datetime.fromisoformat(v.strip().replace("Z", "+00:00"))
            except ValueError:
                raise ValueError(f"{path}: record {i} has {name} = {v!r}, neither epoch seconds/ms nor ISO 8601") from None
            out[i] = (d if d.tzinfo else d.replace(tzinfo=timezone.utc)).timestamp()
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out[i] = v / 1000.0 if abs(v) > MS_EPOCH else v
        else:
            raise ValueError(f"{path}: record {i} has {name} = {v!r}, not a time")
    return out


@dataclass
class Records:
    """One sample's rows as columns: ``t`` (position time, epoch s), ``icao24``, ``lat``, ``lon`` (degrees),
    ``h`` (barometric altitude, m), ``onground``; ``timestamp`` (the row's own time, epoch s); ``exact``:
    the position is timed by its ``last_position``, not by the row."""

    path: Path
    timestamp: np.ndarray
    t: np.ndarray
    icao24: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    onground: np.ndarray
    exact: np.ndarray
    groundspeed: np.ndarray
    track: np.ndarray
    vertical_rate: np.ndarray

    def __len__(self) -> int:
        return len(self.t)


def read_records(path) -> Records:
    """Read one sample file (``.json[.gz]``: a list of records or an object of columns; ``.jsonl[.gz]``: a
    record per line; ``.csv[.gz]``: a header row, then a record per row), its fields under traffic's or OpenSky's
    names (``FIELDS``). Nothing in the file is executed. A ValueError names the file and what is wrong."""
    path = Path(path)
    value = _load_csv(path) if path.name.lower().endswith(CSV_SUFFIXES) else _load_json(path)
    cols, names = _columns(value, path)  # an empty list: empty columns
    if not cols["timestamp"]:
        raise ValueError(f"{path}: holds no records")
    ts = _times(cols["timestamp"], names["timestamp"], path)
    lp = _times(cols["last_position"], names["last_position"], path)
    t = np.where(np.isfinite(lp), lp, ts)
    icao = cols["icao24"]
    if not set(map(type, icao)) <= {str, int, type(None)}:
        bad = next(i for i, v in enumerate(icao) if v is not None and not isinstance(v, (str, int)))
        raise ValueError(f"{path}: record {bad} has icao24 = {icao[bad]!r}, not an address")
    addresses = {v: "" if v is None else str(v).lower() for v in set(icao)}  # a few hundred aircraft
    icao = np.array([addresses[v] for v in icao])
    ground = cols["onground"]
    if set(map(type, ground)) <= {bool, type(None)}:  # the common case, without a Python loop
        onground = np.array(ground, dtype=object) == True  # noqa: E712 (None and False are not on the ground)
    else:
        onground = np.array([bool(v) if isinstance(v, (bool, int, float)) else False for v in ground])
    onground = onground.astype(bool)
    si = names["altitude"] in METRES

    def column(k):  # a numeric field, read as floats
        return _floats(cols[k], names[k], path)

    return Records(path=path, timestamp=ts, t=t, icao24=icao, lat=column("latitude"), lon=column("longitude"),
                   h=column("altitude") * (1.0 if si else FEET), onground=onground, exact=np.isfinite(lp),
                   groundspeed=column("groundspeed") * (1.0 if si else KNOT), track=column("track"),
                   vertical_rate=column("vertical_rate") * (1.0 if si else FEET / 60))


# --- flights ------------------------------------------------------------------------------------
@dataclass
class Flight:
    """One flight's fresh, clean positions: ``t`` (epoch s, increasing), ``lat``, ``lon`` (degrees), ``h`` (m);
    ``exact_time``: each position timed by its ``last_position`` (else by its row, to whole seconds)."""

    id: str
    icao24: str
    t: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    exact_time: np.ndarray
    sample: str = ""  # the sample it comes from (``flights``' ``sample``)


@dataclass
class Flights:
    flights: list[Flight]
    counts: dict = field(default_factory=dict)


def _glitches(t, lat, lon, h, max_speed, max_climb, time_slack, max_gap) -> tuple[np.ndarray, np.ndarray]:
    """``(keep, restart)`` masks over one aircraft's fresh points (see the module docstring, step 3)."""
    n = len(t)
    keep = np.ones(n, bool)
    restart = np.zeros(n, bool)
    if n < 2:
        return keep, restart
    dt = np.diff(t)
    step = local_step(lat, lon)
    climb = np.abs(np.diff(h))
    ok = (step <= max_speed * (dt + time_slack)) & (climb <= max_climb * (dt + time_slack))
    if ok.all():  # the common case: no glitch in the whole sequence
        return keep, restart
    ref, streak = 0, 0
    xyz = geodetic_to_ecef(lat, lon, np.zeros(n)).tolist()  # plain floats: one distance per step below
    t, h = t.tolist(), h.tolist()
    for i in range(1, n):
        gap = t[i] - t[ref]
        if gap > max_gap:
            ref, streak = i, 0
            continue
        d = math.dist(xyz[ref], xyz[i])
        if d <= max_speed * (gap + time_slack) and abs(h[i] - h[ref]) <= max_climb * (gap + time_slack):
            ref, streak = i, 0
            continue
        streak += 1
        keep[i] = False
        if streak > MAX_STREAK:  # the reference was the doubtful one: restart here
            keep[i], restart[i] = True, True
            ref, streak = i, 0
    return keep, restart


def flights(records: Records, max_gap: float = 600.0, max_speed: float = 350.0, max_climb: float = 100.0,
            time_slack: float = 0.5, min_points: int = 10, sample: str = "") -> Flights:
    """Clean one sample's rows and cut them into flights (the module docstring's steps 1-4), each flight's
    ``.sample`` the name ``sample``."""
    r = records
    counts = {"rows": len(r), "onground": int(r.onground.sum())}
    good = np.isfinite(r.t) & np.isfinite(r.lat) & np.isfinite(r.lon) & np.isfinite(r.h) & (r.icao24 != "")
    air = good & ~r.onground
    counts["incomplete"] = int((~good & ~r.onground).sum())
    idx = np.flatnonzero(air)
    order = idx[np.lexsort((r.timestamp[idx], r.icao24[idx]))]  # by aircraft, then row time (stable)
    icao, lat, lon, h, t, ex = r.icao24[order], r.lat[order], r.lon[order], r.h[order], r.t[order], r.exact[order]
    first = np.r_[True, icao[1:] != icao[:-1]]
    fresh = first | np.r_[True, (lat[1:] != lat[:-1]) | (lon[1:] != lon[:-1])]
    counts["stale"] = int((~fresh).sum())
    sel = np.flatnonzero(fresh)
    icao, lat, lon, h, t, ex = icao[sel], lat[sel], lon[sel], h[sel], t[sel], ex[sel]
    out: list[Flight] = []
    counts.update(duplicate_time=0, glitch=0, short=0)
    starts = np.flatnonzero(np.r_[True, icao[1:] != icao[:-1]])
    for a, b in zip(starts, np.r_[starts[1:], len(icao)]):
        ta, la, lo, ha, xa = t[a:b], lat[a:b], lon[a:b], h[a:b], ex[a:b]
        later = np.r_[True, ta[1:] > np.maximum.accumulate(ta)[:-1]]  # strictly after every earlier point
        counts["duplicate_time"] += int((~later).sum())
        ta, la, lo, ha, xa = ta[later], la[later], lo[later], ha[later], xa[later]
        keep, restart = _glitches(ta, la, lo, ha, max_speed, max_climb, time_slack, max_gap)
        counts["glitch"] += int((~keep).sum())
        cut = restart[keep]
        ta, la, lo, ha, xa = ta[keep], la[keep], lo[keep], ha[keep], xa[keep]
        cut |= np.r_[True, np.diff(ta) > max_gap]
        bounds = np.r_[np.flatnonzero(cut), len(ta)]
        for s, e in zip(bounds[:-1], bounds[1:]):
            if e - s < min_points:
                counts["short"] += int(e - s)
                continue
            fid = f"{icao[a]}-{int(math.floor(ta[s]))}"
            out.append(Flight(fid, str(icao[a]), ta[s:e].copy(), la[s:e].copy(), lo[s:e].copy(), ha[s:e].copy(),
                              xa[s:e].copy(), sample))
    counts["flights"] = len(out)
    counts["fresh_points"] = int(sum(len(f.t) for f in out))
    return Flights(out, counts)
