"""Data sets of real flights seen by a simulated radar: ``immnet data adsb`` (docs/real-data.md, "Real flights").

Pipeline: read and clean ADS-B samples into flights (:mod:`immnet.data.adsb`); convert their fresh
positions to the radar site's east-north-up frame (:mod:`immnet.data.geodesy`); lay each flight's scan
times (:func:`immnet.data.radar.scan_times`); smooth the fresh positions with the white-jerk RTS smoother
over the union of their times and the scan times (:mod:`immnet.data.smoother`), evaluated at the scans:
the truth ``[p, v, a]`` per axis; cut windows of ``T`` scans that are wholly covered by the radar and have
truth; measure them (:func:`immnet.data.radar.measure`); split by flight into train/val/test data set
directories that :func:`immnet.data.storage.load_dataset` loads.

A scan has truth only where it lies between two fresh positions at most ``truth_gap`` seconds apart: the
smoother does not invent a trajectory over a gap in the data.

Every random draw comes from a generator seeded by ``(seed, crc32(flight id))`` (per flight: the scan
grid's offset and intervals, the windows' offsets, each window's ``r``, noise and misses, in that order)
or ``(seed, 1)`` (the permutation of flights into splits), so the same samples, parameters and seed give
the same bytes, and one flight's data do not depend on the other flights.
"""

from __future__ import annotations

import dataclasses
import sys
import time
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from immnet import keys
from immnet.data import adsb, radar
from immnet.data.contract import NO_LABEL
from immnet.data.geodesy import enu_to_geodetic, geodetic_to_enu
from immnet.data.scratch import publishing
from immnet.data.smoother import rts_smooth
from immnet.data.spec import check_numbers

SPLITS = ("train", "val", "test")
FORMAT_VERSION = 2  # 2: each split's meta.json names the flight of every window (window_flights)


@dataclass(frozen=True)
class RealSpec:
    """Every parameter of ``immnet data adsb`` (stored in ``meta.json`` as ``params``)."""

    T: int = 200  # scans per window
    dt: float = 1.0  # scan interval (s), or its mean with dt_jitter
    dt_jitter: float = 0.0  # intervals U[dt - dt_jitter, dt + dt_jitter]
    p_miss: float = 0.0  # probability of a missed detection (scans after the second)
    r_min: float = 1.0  # measurement noise std per window, U[r_min, r_max] (m)
    r_max: float = 7.0
    max_range: float = 200_000.0  # slant range of the radar's coverage (m)
    min_elevation: float = 0.0  # lowest elevation the radar sees (degrees): its horizon
    splits: tuple = (0.7, 0.15, 0.15)  # fractions of flights: train, val, test
    max_gap: float = 600.0  # a longer gap between fresh positions starts a new flight (s)
    max_speed: float = 350.0  # glitch: horizontal speed beyond this (m/s) ...
    max_climb: float = 100.0  # ... or vertical speed beyond this (m/s) from the previous kept point
    time_slack: float = 0.5  # allowed timing error of a position in the glitch test (s)
    min_points: int = 10  # shorter flights are dropped
    sigma_h: float = 5.0  # ADS-B horizontal position noise (m), per axis
    sigma_v: float = 3.0  # ADS-B altitude noise (m): its 25 ft quantization
    time_sigma: float = 0.3  # timing error (s) of a position timed by its row (no last_position): 1 s rounding
    q_h: float = 1.0  # white-jerk spectral density of the truth, horizontal (m^2/s^5)
    q_v: float = 0.1  # and vertical
    truth_gap: float = 5.0  # a scan has truth only between fresh positions at most this far apart (s)
    max_position_interval: float = 0.0  # flights whose fresh positions lie further apart, at the median, are left
    # out (s; 0: none): at scans faster than a flight's positions its truth between them is the smoother's interpolation
    max_flights: int = 0  # only the first max_flights flights by id (0: all): a quick look at a large sample
    chunk: int = 1_000_000  # steps x tracks smoothed at once (memory: about 100 bytes each; a longer flight alone)
    # a radar's plots (all three given, each (low, high), drawn per window): noise in slant range (m), azimuth and
    # elevation (degrees), converted to east-north-up with each plot's covariance (meas_cov); (): 3D-LAST's r N(0, I3)
    sigma_range: tuple = ()
    sigma_azimuth: tuple = ()
    sigma_elevation: tuple = ()
    outliers: float = 0.0  # the share of detections whose noise is multiplied by outlier_scale (their meas_cov is not)
    outlier_scale: float = 10.0
    range_km: tuple = ()  # (low, high): a radar per flight, U[low, high] km from it, seeing slant ranges in [low, high]

    def __post_init__(self):
        check_numbers(self)
        if self.max_position_interval < 0:
            raise ValueError(f"max_position_interval must be >= 0 (0: no limit), got {self.max_position_interval}")
        if self.T < 1 or self.min_points < 2 or self.chunk < 1 or self.max_flights < 0:
            raise ValueError(f"T >= 1, min_points >= 2, chunk >= 1 and max_flights >= 0 needed, got {self.T}, "
                             f"{self.min_points}, {self.chunk}, {self.max_flights}")
        radar.check_scan_interval(self.dt, self.dt_jitter)
        if not (0 < self.r_min <= self.r_max):
            raise ValueError(f"the noise levels need 0 < r_min <= r_max, got {self.r_min}, {self.r_max}")
        if not 0 <= self.p_miss < 1:
            raise ValueError(f"p_miss must be in [0, 1), got {self.p_miss}")
        if len(self.splits) != 3 or min(self.splits) < 0 or abs(sum(self.splits) - 1) > 1e-9:
            raise ValueError(f"splits must be three fractions >= 0 (train, val, test) summing to 1, got {self.splits}")
        for name in ("max_range", "max_gap", "max_speed", "max_climb", "sigma_h", "sigma_v", "q_h", "q_v", "truth_gap"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in PAIRS:
            v = getattr(self, name)
            if v and not (len(v) == 2 and all(np.isfinite(float(x)) for x in v) and 0 < float(v[0]) <= float(v[1])):
                raise ValueError(f"{name} is a pair LOW,HIGH with 0 < LOW <= HIGH, got {tuple(v)}")
        radar.check_plot_settings([n for n in PAIRS[:3] if getattr(self, n)], self.outliers, self.outlier_scale)

    @property
    def plots(self) -> bool:
        """The radar measures plots (range, azimuth, elevation): ``sigma_*`` given."""
        return bool(self.sigma_range)

    @property
    def writes_cov(self) -> bool:
        """The data hold each detection's covariance ``meas_cov``: plots, outliers or a placed radar asked for (a set
        of the defaults keeps the bytes it had without them)."""
        return self.plots or self.outliers > 0 or bool(self.range_km)

    def to_dict(self) -> dict:
        """The parameters as JSON; those of plots, outliers and placement only where not their defaults (a set of
        the defaults keeps the meta.json it had without them)."""
        d = dataclasses.asdict(self)
        d["splits"] = [float(f) for f in self.splits]
        for name in (*PAIRS, "outliers", "outlier_scale"):
            if d[name] == _DEFAULTS[name]:
                del d[name]
            elif name in PAIRS:
                d[name] = [float(x) for x in d[name]]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "RealSpec":
        """The spec of ``to_dict`` (a set's ``meta["params"]``), its JSON lists tuples again."""
        return cls(**{**d, "splits": tuple(d["splits"]), **{k: tuple(d[k]) for k in PAIRS if k in d}})


PAIRS = ("sigma_range", "sigma_azimuth", "sigma_elevation", "range_km")
"""RealSpec's (low, high) fields, () where not asked for."""
_DEFAULTS = {f.name: f.default for f in dataclasses.fields(RealSpec)}


def _log(progress: bool, msg: str) -> None:
    if progress:
        print(f"[adsb] {msg}", file=sys.stderr, flush=True)


def turn_rate(states: np.ndarray) -> np.ndarray:
    """The horizontal turn rate ``(vx ay - vy ax) / (vx^2 + vy^2)`` (rad/s) of states ``[..., 9]``."""
    vx, ax, vy, ay = states[..., 1], states[..., 2], states[..., 4], states[..., 5]
    return (vx * ay - vy * ax) / np.maximum(vx * vx + vy * vy, 1e-9)


def _has_truth(fresh_t: np.ndarray, scans: np.ndarray, gap: float) -> np.ndarray:
    """Scans between two fresh positions at most ``gap`` apart (or at one)."""
    i = np.searchsorted(fresh_t, scans, side="right")  # fresh_t[i - 1] <= scan < fresh_t[i]
    at = (i > 0) & (fresh_t[np.maximum(i - 1, 0)] == scans)
    inside = (i > 0) & (i < len(fresh_t))
    span = fresh_t[np.minimum(i, len(fresh_t) - 1)] - fresh_t[np.maximum(i - 1, 0)]
    return at | (inside & (span <= gap))


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(starts, stops)`` of the runs of True in ``mask``."""
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(np.int8), 0]))
    return edges[::2], edges[1::2]


def _measurement_var(f: adsb.Flight, enu: np.ndarray, spec: RealSpec) -> np.ndarray:
    """Variance ``[n, 3]`` of each fresh position: ``sigma_h^2 + (v time_sigma)^2`` horizontally (``v`` the
    speed between neighbouring points) where the point is timed by its row, ``sigma_v^2`` vertically."""
    step = np.linalg.norm(np.diff(enu[:, :2], axis=0), axis=1) / np.maximum(np.diff(f.t), 1e-3)
    speed = np.r_[step[:1], (step[:-1] + step[1:]) / 2, step[-1:]] if len(step) else np.zeros(1)
    h = spec.sigma_h ** 2 + np.where(f.exact_time, 0.0, (speed * spec.time_sigma) ** 2)
    return np.stack([h, h, np.full_like(h, spec.sigma_v ** 2)], -1)


def truth(flights: list[adsb.Flight], sites: list, spec: RealSpec, seed: int, progress: bool = False) -> list[dict]:
    """Per flight: scan times ``t [S]``, truth ``states [S, 9]`` (NaN rows without truth) and ``valid [S]``
    (truth and radar coverage), from the smoother over fresh positions and scans (module docstring).
    ``sites``: the radar site ``(lat, lon, h)`` of each flight."""
    prepared = []
    for f, site in zip(flights, sites):
        rng = np.random.default_rng([int(seed), 0, zlib.crc32(f.id.encode())])
        scans = radar.scan_times(f.t[0], f.t[-1], spec.dt, spec.dt_jitter, rng)
        enu = geodetic_to_enu(f.lat, f.lon, f.h, site)
        ok = _has_truth(f.t, scans, spec.truth_gap)
        prepared.append(dict(flight=f, rng=rng, scans=scans, enu=enu, var=_measurement_var(f, enu, spec), ok=ok))
    steps = [len(p["scans"]) + len(p["flight"].t) for p in prepared]
    # a flight without T scans of truth in a row can have no window: it is not smoothed (nothing else changes)
    short = [i for i, p in enumerate(prepared) if not any(b - a >= spec.T for a, b in zip(*_runs(p["ok"])))]
    for i in short:
        p = prepared[i]
        p["states"], p["valid"] = np.full((len(p["scans"]), 9), np.nan), np.zeros(len(p["scans"]), bool)
    order = sorted(set(range(len(prepared))) - set(short), key=lambda i: (steps[i], i))
    chunks = []
    for i in order:  # flights of similar lengths together, at most `chunk` x 3 tracks of steps per chunk
        if chunks and steps[i] * 3 * (len(chunks[-1]) + 1) <= spec.chunk:
            chunks[-1].append(i)
        else:
            chunks.append([i])
    q = np.array([spec.q_h, spec.q_h, spec.q_v])
    done = 0
    for members in chunks:
        chunk = [prepared[i] for i in members]
        tracks = [(p["flight"].t, p["enu"], p["var"], p["scans"], p["flight"].t[0], p["ok"]) for p in chunk]
        for p, s in zip(chunk, smooth_at_scans(tracks, q)):
            p["states"] = s
            p["valid"] = p["ok"] & _covered(np.nan_to_num(s[:, [0, 3, 6]], nan=np.inf), spec)
        done += len(chunk)
        _log(progress, f"truth: {done}/{len(order)} flights smoothed")
    return prepared


def smooth_at_scans(tracks: list[tuple], q: np.ndarray) -> list[np.ndarray]:
    """The truth ``[S, 9]`` at the scans of each track ``(fresh times [n], ENU [n, 3], their variances [n, 3], scans
    [S], time origin, has truth [S])``, NaN rows where it has none: one run of the white-jerk RTS smoother (spectral
    densities ``q [3]`` per axis) over each track's fresh positions and scans together, the tracks padded to the
    longest."""
    K, B = max(len(fresh) + len(scans) for fresh, _, _, scans, _, _ in tracks), 3 * len(tracks)
    t, z, var = np.empty((K, B)), np.full((K, B), np.nan), np.ones((K, B))
    where = []
    for j, (fresh, enu, v, scans, origin, _) in enumerate(tracks):
        times = np.r_[fresh, scans] - origin
        srt = np.argsort(times, kind="stable")
        where.append(np.flatnonzero(srt >= len(fresh)))  # the steps of the scans, in scan order
        n = len(times)
        cols = slice(3 * j, 3 * j + 3)
        t[:n, cols] = times[srt][:, None]
        t[n:, cols] = times[srt][-1]
        z[:n, cols] = np.r_[enu, np.full((len(scans), 3), np.nan)][srt]
        var[:n, cols] = np.r_[v, np.ones((len(scans), 3))][srt]
    xs = rts_smooth(t, z, var, np.tile(q, len(tracks)))
    out = []
    for j, track in enumerate(tracks):
        s = xs[where[j], 3 * j : 3 * j + 3].reshape(-1, 9)  # [S, axis, (p, v, a)] -> the 9-state layout
        s[~track[-1]] = np.nan
        out.append(s)
    return out


def _covered(pos: np.ndarray, spec: RealSpec) -> np.ndarray:
    """Where the radar sees ``pos [S, 3]``: within ``max_range`` above its horizon, and with ``range_km`` a slant range
    in ``[low, high]`` km."""
    if not spec.range_km:
        return radar.covered(pos, spec.max_range, spec.min_elevation)
    low, high = (1000.0 * float(v) for v in spec.range_km)
    rho = radar.polar(pos)[0]
    return radar.covered(pos, min(spec.max_range, high), spec.min_elevation) & (rho >= low)


def windows(p: dict, spec: RealSpec) -> list[int]:
    """Start indices of non-overlapping windows of ``T`` valid scans: in each run of valid scans of length
    ``L``, from a random offset in ``0..L mod T`` on."""
    starts = []
    for a, b in zip(*_runs(p["valid"])):
        L = b - a
        if L < spec.T:
            continue
        s0 = a + int(p["rng"].integers(0, L % spec.T + 1))
        starts += list(range(s0, b - spec.T + 1, spec.T))
    return starts


def simulate(p: dict, spec: RealSpec, with_cov: bool = False) -> list[tuple]:
    """The radar's windows of one flight (``truth``'s ``p``; draws from its generator): per window ``(states [T, 9],
    measurements [T, 3], r, scans [T])``, the scans' times in epoch seconds; ``with_cov``: and each detection's
    covariance ``[T, 3, 3]`` (m^2, NaN where missed). 3D-LAST's noise ``r N(0, I3)`` (covariance ``r^2 I``) unless
    ``spec.plots`` (a radar's plots, :func:`immnet.data.radar.plots` with ``spec``'s ``sigma_*``, ``p_miss`` and
    outliers); a share ``outliers`` of the detections with ``outlier_scale`` times the noise (drawn after the rest of
    the window's, none drawn at share 0)."""
    out = []
    for s in windows(p, spec):
        st = p["states"][s : s + spec.T]
        pos = st[:, [0, 3, 6]]
        if spec.plots:
            z, r, cov = radar.plots(pos, spec.sigma_range, spec.sigma_azimuth, spec.sigma_elevation, spec.p_miss,
                                    spec.outliers, spec.outlier_scale, p["rng"])
        else:
            r = p["rng"].uniform(spec.r_min, spec.r_max)
            z = radar.measure(pos, r, spec.p_miss, p["rng"])
            if spec.outliers > 0:
                wild = p["rng"].random(len(z)) < spec.outliers
                z[wild] = pos[wild] + spec.outlier_scale * (z[wild] - pos[wild])
            cov = np.where(np.isnan(z).any(-1)[:, None, None], np.nan, r * r * np.eye(3))
        out.append((st, z, float(r), p["scans"][s : s + spec.T], *((cov,) if with_cov else ())))
    return out


def place_site(f: adsb.Flight, range_km, seed: int) -> tuple[float, float, float]:
    """A radar for flight ``f``: at height 0, ``U[low, high]`` km (``range_km``) from the flight's median latitude and
    longitude on a bearing ``U[0, 360)`` degrees, drawn from a generator of its own, ``(seed, 3, crc32(flight id))``."""
    rng = np.random.default_rng([int(seed), 3, zlib.crc32(f.id.encode())])
    d, b = 1000.0 * rng.uniform(*range_km), rng.uniform(0.0, 2 * np.pi)
    centre = radar.median_site(f.lat, f.lon)
    lat, lon, _ = enu_to_geodetic(np.array([d * np.sin(b), d * np.cos(b), 0.0]), centre)
    return float(lat), float(lon), 0.0


def partition(ids: list[str], fractions, seed: int) -> dict[str, list[str]]:
    """The flights ``ids`` (sorted) of each split: a permutation drawn from ``(seed, 1)``, cut into ``round(f n)``
    flights for validation and test (at least 1 where ``f > 0``) and the rest for train; a ValueError if a split
    with ``f > 0`` would be empty. A function of the flights selected and the seed alone, not of the scan settings,
    so the sets of one region at several scan intervals (a flight may have windows at one and none at another)
    split its flights alike."""
    n = len(ids)
    f_train, f_val, f_test = (float(f) for f in fractions)
    val = max(int(round(f_val * n)), 1 if f_val > 0 else 0)
    test = max(int(round(f_test * n)), 1 if f_test > 0 else 0)
    train = n - val - test
    if f_train == 0:
        val, train = val + train, 0
    if train < 0 or (f_train > 0 and train < 1):
        raise ValueError(f"{n} flight(s) cannot fill the splits {list(fractions)} (each split with a "
                         f"positive fraction needs a flight); use fewer splits or more data")
    perm = np.random.default_rng([int(seed), 1]).permutation(n)
    cut = {"train": perm[:train], "val": perm[train : train + val], "test": perm[train + val :]}
    return {k: sorted(ids[i] for i in v) for k, v in cut.items()}


def position_interval(flight: adsb.Flight) -> float:
    """The median time between a flight's fresh positions (s): about 1 for state vectors recorded every second,
    5 or 10 for traffic's resampled samples."""
    return float(np.median(np.diff(flight.t)))


def select_flights(flights: list[adsb.Flight], spec: RealSpec) -> tuple[list[adsb.Flight], list[adsb.Flight]]:
    """``(kept, sparse)``: the flights a set takes, as ``make_adsb`` selects them after the ids are made unique,
    and those left out as ``sparse``: a flight whose fresh positions lie more than ``spec.max_position_interval``
    apart (median) is left out, then only the first ``spec.max_flights`` by id are kept (0: no limit for either)."""
    kept, sparse = flights, []
    if spec.max_position_interval:
        kept = []
        for f in flights:
            (kept if position_interval(f) <= spec.max_position_interval else sparse).append(f)
    if spec.max_flights:
        kept = sorted(kept, key=lambda f: f.id)[: spec.max_flights]
    return kept, sparse


def set_flights(meta: dict, where="the set") -> tuple[list[adsb.Flight], dict[str, adsb.Records]]:
    """``(flights, {sample name: records})``: the flights a real-flight set was built from, read again from the
    samples its ``meta`` names with its parameters and selected as ``make_adsb`` selects them (ids made unique, each
    ``.sample`` named, ``max_position_interval`` and ``max_flights`` applied), for a script that needs what the set's
    windows do not keep. A ValueError naming ``where`` if a sample file is not the one the set was built from."""
    spec = RealSpec.from_dict(meta["params"])
    flights, records = [], {}
    for sample in meta["samples"]:
        path = adsb.resolve_sample(sample["name"])
        if adsb.file_digest(path) != sample["sha256"]:
            raise ValueError(f"{path}: not the file {where} was built from (its SHA-256 differs)")
        rec = records[sample["name"]] = adsb.read_records(path)
        flights += adsb.flights(rec, spec.max_gap, spec.max_speed, spec.max_climb, spec.time_slack, spec.min_points,
                                sample["name"]).flights
    unique_ids(flights)
    return select_flights(flights, spec)[0], records


def unique_ids(flights: list[adsb.Flight]) -> None:
    """Flight ids unique across samples, in place: a repeated one gets #2, #3, ... in the order of ``flights`` (the
    samples' order), as the data sets' ``flights`` and ``window_flights`` name them."""
    seen: dict[str, int] = {}
    for f in flights:
        seen[f.id] = seen.get(f.id, 0) + 1
        if seen[f.id] > 1:
            f.id = f"{f.id}#{seen[f.id]}"


def make_adsb(out, samples: list[str], spec: RealSpec = RealSpec(), seed: int = 0, site=None,
              npz: bool = False, overwrite: bool = False, progress: bool = False,
              skip_unreadable: bool = False, splits_from=None) -> dict:
    """Build the data sets ``out/{train,val,test}`` from ADS-B samples (names or files); return the meta.

    ``splits_from``: a split directory (or the ``OUT``) of a set of the same samples, whose partition of the
    flights this set takes instead of drawing its own (``spec.splits`` unused): each flight in the split the
    reference names it in, a flight the reference does not name left out (counted as ``unsplit``). Sets of one
    region at several scan intervals need one partition, or a model trained on one set's training flights is
    scored on its test flights at another interval (a flight with windows at one interval may have none at
    another, which changes the permutation of the flights with windows).

    ``site``: ``(lat, lon, h)`` of the radar for every sample; default one radar per sample, at the median
    position of its flights at height 0 (samples from several regions each get their own). A split with
    fraction 0 is not written. ``npz``: also ``out/<split>.npz``. ``skip_unreadable``: a sample refused
    by :func:`immnet.data.adsb.read_records` (not state vectors, malformed) is skipped and listed in
    ``meta.json``'s ``skipped`` instead of stopping the run.
    """
    from immnet.data.storage import REAL_FORMAT, _check_out, export_npz, write_arrays

    start = time.perf_counter()
    out = Path(out)
    if not samples:
        raise ValueError("no ADS-B samples given")
    if site is not None and spec.range_km:
        raise ValueError("give --site (one radar for every sample) or --range-km (a radar per flight), not both")
    _check_out(out, overwrite)
    flights, sources, counts, skipped, sites = [], [], {}, [], {}
    for name in samples:
        path = adsb.resolve_sample(name)
        digest = adsb.file_digest(path)
        twice = next((s["name"] for s in sources if s["sha256"] == digest), None)
        if twice is not None:  # its flights would be counted twice, and could land in two splits
            raise ValueError(f"{path}: the same file as sample {twice!r}; give each sample once")
        try:
            rec = adsb.read_records(path)
        except ValueError as err:
            if not skip_unreadable:
                raise
            why = str(err).replace(str(path), path.name)  # no machine's paths in meta.json
            skipped.append({"name": str(name), "error": why})
            _log(progress, f"skipped {name}: {why}")
            continue
        got = adsb.flights(rec, spec.max_gap, spec.max_speed, spec.max_climb, spec.time_slack, spec.min_points,
                           str(name))
        if got.flights:
            sites[str(name)] = (tuple(float(v) for v in site) if site is not None else
                                radar.median_site(np.concatenate([f.lat for f in got.flights]),
                                                  np.concatenate([f.lon for f in got.flights])))
        flights += got.flights
        for k, v in got.counts.items():
            counts[k] = counts.get(k, 0) + v
        sources.append({"name": str(name), "file": path.name, "sha256": digest, "counts": got.counts})
        _log(progress, f"read {name}: {got.counts['rows']} rows, {got.counts['flights']} flights, "
                       f"{got.counts['fresh_points']} fresh points ({time.perf_counter() - start:.1f} s)")
    if not flights:
        raise ValueError(f"no flight of at least {spec.min_points} airborne fresh positions in {', '.join(map(str, samples))}")
    unique_ids(flights)
    flights, sparse = select_flights(flights, spec)  # after the ids and sites: a kept flight's windows are a full set's
    per_sample = {src["name"]: src["counts"] for src in sources}
    reference = where = None
    if splits_from is not None:  # read and checked before any flight is smoothed
        reference, where = reference_partition(splits_from, {s["sha256"] for s in sources})
    counts["sparse"] = len(sparse)
    for name, c in per_sample.items():
        c.update(sparse=sum(f.sample == name for f in sparse), windows=0, flights_with_windows=0)
    if reference is not None:
        counts["unsplit"] = 0
    if not flights:
        raise ValueError(f"no flight whose fresh positions are at most {spec.max_position_interval:g} s apart "
                         f"(median) in {', '.join(map(str, samples))}")
    # with range_km a radar per flight, placed from the flight's own generator; else its sample's
    flight_sites = {f.id: place_site(f, spec.range_km, seed) if spec.range_km else sites[f.sample] for f in flights}
    prepared = truth(flights, [flight_sites[f.id] for f in flights], spec, seed, progress)
    rows = {}
    for p in sorted(prepared, key=lambda p: p["flight"].id):
        wins = [(st, z, r, scans - scans[0], *cov) for st, z, r, scans, *cov in simulate(p, spec, spec.writes_cov)]
        if wins and reference is not None and p["flight"].id not in reference:
            counts["unsplit"] += 1  # a flight with windows that the reference does not split: left out
            continue
        if wins:
            rows[p["flight"].id] = wins
        c = per_sample[p["flight"].sample]
        c["windows"] += len(wins)
        c["flights_with_windows"] += bool(wins)
    ids = sorted(rows)
    if not ids and reference is not None and counts["unsplit"]:
        raise ValueError(f"--splits-from {where}: it names none of these flights with windows")
    if not ids:
        raise ValueError(f"no window of T={spec.T} scans with truth within {spec.max_range:g} m of the radar "
                         f"({', '.join(f'{k}: {v}' for k, v in sites.items())})")
    if reference is not None:
        members = {k: sorted(i for i in ids if reference[i] == k) for k in SPLITS}
    else:  # drawn over every flight selected, with windows at these scan settings or not: one partition per region
        members = partition(sorted(p["flight"].id for p in prepared), spec.splits, seed)
        members = {k: [i for i in v if i in rows] for k, v in members.items()}
        empty = [k for k, f in zip(SPLITS, spec.splits) if float(f) > 0 and not members[k]]
        if empty:
            raise ValueError(f"no flight with windows in split(s) {', '.join(empty)} of the {len(prepared)} flight(s) "
                             f"({len(ids)} with windows of T={spec.T} scans); use fewer splits or more data")
    counts["windows"] = {k: sum(len(rows[i]) for i in members[k]) for k in SPLITS}
    counts["flights_with_windows"] = len(ids)
    meta = {
        "format": REAL_FORMAT, "format_version": FORMAT_VERSION, "seed": int(seed),
        "samples": [{k: v for k, v in s.items() if k != "counts"} for s in sources],
        "site_from": "given" if site is not None else "median of each sample",
        "sites": {k: {"lat": v[0], "lon": v[1], "h": v[2]} for k, v in sites.items()}, "skipped": skipped,
        "params": spec.to_dict(), "counts": counts, "counts_per_sample": {s["name"]: s["counts"] for s in sources},
        "flights": members,
    }
    if reference is not None:
        meta["splits_from"] = where
    if spec.range_km:  # each flight's own radar: "sites" by flight id
        meta["site_from"] = (f"one radar per flight, U[{spec.range_km[0]:g}, {spec.range_km[1]:g}] km from its median "
                             f"position, height 0")
        meta["sites"] = {i: dict(zip(("lat", "lon", "h"), flight_sites[i])) for i in sorted(flight_sites)}
    with publishing(out) as tmp:
        tmp.mkdir()
        for split in SPLITS:
            wins = [w for i in members[split] for w in rows[i]]
            if not wins:
                continue
            states = np.stack([w[0] for w in wins])
            arrays = {
                keys.STATES: states, keys.MEASUREMENTS: np.stack([w[1] for w in wins]),
                keys.MODE: np.full(states.shape[:2], NO_LABEL, np.int64), keys.TURN_RATE: turn_rate(states),
                keys.R: np.array([w[2] for w in wins]), keys.DT: np.full(len(wins), spec.dt),
                keys.TIME: np.stack([w[3] for w in wins]),
            }
            if spec.writes_cov:
                arrays[keys.MEAS_COV] = np.stack([w[4] for w in wins])
            write_arrays(tmp / split, arrays,
                         {**meta, "split": split, "window_flights": [i for i in members[split] for _ in rows[i]]})
            if npz:
                export_npz(tmp / split, tmp / f"{split}.npz")
            _log(progress, f"wrote {split}: {len(wins)} windows of {len(members[split])} flights")
    meta["seconds"] = round(time.perf_counter() - start, 2)
    return meta


def _real_split(data: Path, out: Path, overwrite: bool, what: str):
    """``(td, meta)`` of ``data``, one split of ``immnet data adsb``, for a writer of a set derived from it (``what``
    it does, for the messages); refuses, by name, a file or missing path, an ``out`` that is ``data`` or not empty,
    and a set of another format (3D-LAST's has no flights)."""
    from immnet.data.storage import REAL_FORMAT, _check_out, load_dataset

    if not data.is_dir():
        raise ValueError(f"{data}: {what} needs a real-flight data set directory (immnet data adsb's OUT/train, "
                         f"OUT/val or OUT/test), not {'a file' if data.exists() else 'a missing path'}")
    if out.resolve() == data.resolve():
        raise ValueError(f"{out}: {what} would replace its own source; give another --out")
    _check_out(out, overwrite)
    td, meta = load_dataset(data)
    if meta.get("format") != REAL_FORMAT:
        raise ValueError(f"{data}: format {meta.get('format')!r} is not real flights; {what} needs a set written "
                         f"by `immnet data adsb`")
    return td, meta


def _write_split(out: Path, arrays: dict, meta: dict) -> dict:
    """Write ``arrays`` as the data set ``out`` (through a temporary sibling) with ``meta``, less the fields
    ``write_arrays`` counts again (``n``, ``T``, ``counts_per_mode``, ``dtype``); return the meta written."""
    from immnet.data.storage import load_dataset, write_arrays

    kept = {k: v for k, v in meta.items() if k not in ("n", "T", "counts_per_mode", "dtype")}
    with publishing(out) as tmp:
        write_arrays(tmp, arrays, kept)
    return load_dataset(out)[1]


def subset_flights(data, out, flights: float | None = None, seed: int = 0, overwrite: bool = False,
                   without=()) -> dict:
    """Write the windows of some of a real-flight set's flights as the data set ``out``; return its meta.

    ``data``: one split of ``immnet data adsb`` (a directory whose ``meta.json`` names each window's flight,
    format version 2). ``without``: splits of real-flight sets (``OUT/train``, ...) whose flights are left out
    first: the flights a model trained, tuned or chose on, wherever they were (a set of the same samples at
    another scan interval may split them otherwise). ``flights``: how many of the flights left to keep, a count
    (a whole number >= 1) or a fraction in (0, 1) of them (rounded, at least one); None: all of them (with
    ``without``). The flights are taken in a seeded permutation of their ids, so that with one seed a smaller
    subset is part of every larger one (a data-scaling curve adds flights, it does not swap them). Each kept
    window is the source's row, byte for byte, in the source's order; ``meta.json`` is the source's with this
    split's ``flights`` and ``window_flights`` narrowed and ``subset`` added (``flights``, ``of_flights``,
    ``windows``, ``of_windows``, ``seed``, and with ``without`` the splits named and the flights they took out).
    """
    data, out = Path(data), Path(out)
    if flights is None and not without:
        raise ValueError("a subset needs --flights, --without or both")
    td, meta = _real_split(data, out, overwrite, "a subset of flights")
    owners = window_flights(meta, td.batch_size[0], data)
    ids = sorted(set(owners))
    seen = _flights_of(without, meta)
    left = [f for f in ids if f not in seen]
    if not left:
        raise ValueError(f"{data}: every flight of it is in {', '.join(map(str, without))}; no window is left")
    k = len(left) if flights is None else _flight_count(flights, len(left), data)
    chosen = {left[i] for i in np.random.default_rng([int(seed), 2]).permutation(len(left))[:k]}
    rows = np.array([i for i, f in enumerate(owners) if f in chosen])
    arrays = {key: td[key].numpy()[rows] for key in td.keys()}
    subset = {"flights": k, "of_flights": len(ids), "windows": len(rows), "of_windows": len(owners), "seed": int(seed)}
    if without:
        subset["without"] = {"splits": [str(w) for w in without], "flights": len(ids) - len(left)}
    return _write_split(out, arrays, {**meta, "flights": {**meta.get("flights", {}), meta.get("split"): sorted(chosen)},
                                      "window_flights": [owners[i] for i in rows], "subset": subset})


def _flights_of(splits, meta: dict) -> set[str]:
    """The flights the real-flight ``splits`` (directories) name, each checked to be a split of a set of the same
    samples as the set ``meta`` describes, so that its flight ids are that set's."""
    from immnet.data.storage import sample_digests

    digests = sample_digests(meta)
    seen: set[str] = set()
    for split in splits:
        split = Path(split)
        if not (split / "meta.json").is_file() and any((split / k / "meta.json").is_file() for k in SPLITS):
            raise ValueError(f"--without {split}: not one split of a set but a set's OUT; give its splits "
                             f"(OUT/train, OUT/val, ...)")
        other = _reference_meta(split, digests, "--without")
        if other.get("split") not in SPLITS:
            raise ValueError(f"--without {split}: not one split of a set (OUT/train, OUT/val or OUT/test)")
        seen |= set(other["flights"][other["split"]])
    return seen


def reference_partition(path, digests: set[str]) -> tuple[dict[str, str], str]:
    """``({flight id: split}, where)``: the partition of the flights of the real-flight set at ``path`` (one of its
    split directories, or its ``OUT``), checked to be made from some of the samples of SHA-256 ``digests``."""
    path = Path(path)
    if not (path / "meta.json").is_file():  # the set's OUT: its first split
        path = next((path / k for k in SPLITS if (path / k / "meta.json").is_file()), path)
    meta = _reference_meta(path, digests, "--splits-from")
    flights = meta.get("flights")
    if not isinstance(flights, dict) or not all(isinstance(flights.get(k, []), list) for k in SPLITS):
        raise ValueError(f"--splits-from {path}: meta.json names no partition of its flights ('flights')")
    partition = {f: k for k in SPLITS for f in flights.get(k, [])}
    return partition, str(path)


def _reference_meta(path: Path, digests: set[str], option: str) -> dict:
    """The ``meta.json`` of a real-flight split at ``path`` (read as JSON), refused by name unless it is one and it
    was made from at least one of the samples of SHA-256 ``digests`` (its flight ids are then theirs)."""
    from immnet.data.storage import REAL_FORMAT, read_json, sample_digests

    if not (path / "meta.json").is_file():
        raise ValueError(f"{option} {path}: not a data set directory (no meta.json)")
    meta = read_json(path / "meta.json", f"{option} {path}/meta.json")
    if not isinstance(meta, dict) or meta.get("format") != REAL_FORMAT:
        raise ValueError(f"{option} {path}: not a set of `immnet data adsb` (format "
                         f"{meta.get('format') if isinstance(meta, dict) else None!r})")
    if not digests & sample_digests(meta):
        raise ValueError(f"{option} {path}: made from none of these samples; its flights cannot be theirs")
    return meta


def turned_flights(data, out, turns: float, seed: int = 0, bank=(10.0, 30.0), segment=(20.0, 120.0),
                   overwrite: bool = False) -> dict:
    """Write a real-flight set's windows with turns added to a share ``turns`` of them as the data set ``out``;
    return its meta.

    ``data``: one split of ``immnet data adsb``. Each window is flown through ``FlightAugment``'s added turns
    (``immnet.data.augment``: segments of ``segment`` seconds, half of them turning at a coordinated turn's rate
    for a bank drawn from ``bank`` degrees) and measured again with its own ``r`` (its missed scans stay missed);
    no rotation, so each window stays where its radar saw it. A validation set of the training region's own
    flights that turns as much as patterns and orbits do (docs/notebook/real-flights.md, "Turns added to the training
    flights"). ``meta.json`` is the source's with ``turns`` added (``turns``, ``bank``, ``segment``, ``seed``)."""
    import torch

    from immnet.data.augment import FlightAugment
    from immnet.data.storage import as_batch

    data, out = Path(data), Path(out)
    td, meta = _real_split(data, out, overwrite, "adding turns")
    aug = FlightAugment(rotate=False, renoise=True, r_range=None, seed=seed, turns=turns, turn_bank=bank,
                        turn_segment=segment)
    arrays = {k: v.numpy() for k, v in aug(as_batch(td, torch.float64), 0).items()}
    turns = {"turns": aug.turns, "bank": list(aug.turn_bank), "segment": list(aug.turn_segment), "seed": int(seed)}
    return _write_split(out, arrays, {**meta, "turns": turns})


def window_flights(meta: dict, n: int, where) -> list[str]:
    """The flight of each of a real-flight set's ``n`` windows, from its ``meta.json`` (format version 2); a
    ValueError naming ``where`` if the file does not say them."""
    owners = meta.get("window_flights")
    if not isinstance(owners, list) or len(owners) != n:
        raise ValueError(f"{where}: meta.json does not name the flight of each window (format_version "
                         f"{meta.get('format_version')}; 2 does): write the set again with `immnet data adsb`")
    return owners


def _flight_count(flights: float, n: int, data) -> int:
    """``flights`` (a count, or a fraction in (0, 1)) of ``n`` flights, checked."""
    f = float(flights)
    if not np.isfinite(f) or f <= 0:
        raise ValueError(f"--flights must be a count >= 1 or a fraction in (0, 1), got {flights!r}")
    if f < 1:
        return max(1, int(round(f * n)))
    if f != int(f):
        raise ValueError(f"--flights {flights!r}: a count must be a whole number (a fraction is below 1)")
    if int(f) > n:
        raise ValueError(f"{data}: --flights {int(f)} but the set has {n} flights")
    return int(f)
