"""Multi-target scenes: several aircraft seen together by one radar, with missed detections and clutter
(``immnet data scenes``; docs/data.md, "Multi-target scenes").

A scene is what a radar hands a multi-target tracker: per scan a time and an unordered set of plots, none saying
which aircraft it belongs to. Two kinds:

* **ADS-B scenes** (``kind = "adsb"``): the real flights of one ADS-B sample (:mod:`immnet.data.adsb`) seen by a
  radar at a site (default the median position of the sample's flights, height 0), in a window of ``duration``
  seconds during which between ``min_targets`` and ``max_targets`` aircraft are in the radar's cover at every
  scan. The truth at the scans is the white-jerk RTS smoother over each flight's fresh positions, as for
  ``immnet data adsb`` (:mod:`immnet.data.real`); a scan has an aircraft's truth only between two of its fresh
  positions at most ``truth_gap`` seconds apart.
* **3D-LAST scenes** (``kind = "3d-last"``): ``targets`` maneuvering trajectories of the 3D-LAST generator
  (:mod:`immnet.data.generate`, simulated at a step of ``last_step`` seconds and taken at the scans) in one volume
  around the radar at the origin, ``crossing_pairs`` of them made to cross (one trajectory rotated and moved
  so that at a scan in the middle half of the scene it passes within ``crossing_miss`` metres of the other, at
  30-150 degrees) and ``close_pairs`` to fly side by side (within 10 degrees of each other's heading,
  ``close_separation`` metres apart). Rotating a trajectory about the vertical and moving it keeps its
  motion (CV, CA and coordinated turns alike).

The radar, for both kinds: scans at ``t_0 + sum dt_j``, ``dt_j ~ U[dt - dt_jitter, dt + dt_jitter]``
(:func:`immnet.data.radar.scan_times`), every plot of a scan stamped with the scan's time. An aircraft in cover
(slant range <= ``max_range``, elevation >= ``min_elevation``) is detected with probability ``pd``; its plot is
its true range, azimuth and elevation plus independent Gaussian noise (``sigma_range`` m, ``sigma_azimuth_deg``,
``sigma_elevation_deg``). Clutter: a Poisson number of plots of mean ``clutter`` per scan, uniform in range
``[min_range, max_range]``, azimuth ``[0, 360)`` degrees and elevation ``[min_elevation, max_elevation]``.
The plots of a scan are shuffled. Each plot is converted to east-north-up (:func:`immnet.data.radar.from_polar`)
with its first-order covariance at the measured range and angles (:func:`immnet.data.radar.polar_covariance`),
which is what a tracker can know.

Reproducibility: an ADS-B scene draws everything (scan times, then per scan detections, noise, clutter, order)
from a generator seeded by ``(seed, crc32(sample name), start time in whole seconds)``, so one scene does not
depend on which others are made; the windows are chosen by a permutation drawn from ``(seed, crc32(sample))``.
A 3D-LAST scene ``i`` draws its trajectories from a torch generator of ``(seed, i)`` and the rest from
``(seed, 2, i)``.

Splits: scenes of the samples ``TRAIN_SAMPLES`` (``collections/quickstart``) are for training and tuning
(``train``), scenes of any other sample for evaluation only (``test``); 3D-LAST scenes are ``train`` with
``--last-split train`` (default ``test``). A scene holds only one sample's flights.

On disk (:func:`save_scene`, :func:`load_scene`): one ``.npz`` per scene, read with ``allow_pickle=False``
(nothing in it is executed). Scans are laid end to end, ``*_offsets [S + 1]`` bounding each scan's rows::

    t [S]                 scan times (s; epoch seconds for ADS-B scenes, from 0 for 3D-LAST)
    plot_offsets [S + 1]  scan k's plots are rows plot_offsets[k]:plot_offsets[k + 1]
    plots [P, 3]          ENU (m)                 plot_polar [P, 3]  range (m), azimuth, elevation (rad)
    plot_cov [P, 3, 3]    ENU covariance (m^2)    plot_source [P]    aircraft index, -1 clutter (scoring only)
    truth_offsets [S + 1] truth_states [Q, 9]     truth_id [Q]       the aircraft in cover at each scan (scoring only)
    aircraft [A]          flight ids (ADS-B) or target names (3D-LAST)
    site [3]              radar (lat, lon, h) for ADS-B scenes; NaN for 3D-LAST (ENU at the radar)
    meta                  JSON text: kind, name, split, sample, seed, spec, counts

``truth_states`` is ``[x, vx, ax, y, vy, ay, z, vz, az]`` (m, m/s, m/s^2), the layout of every data set. The
truth (``truth_*``, ``plot_source``) is for scoring only: a tracker reads ``t``, ``plots`` and ``plot_cov``
(:meth:`Scene.scans`). :func:`write_plots_csv` writes a scene's plots as ``t,range,azimuth,elevation``
(m, degrees clockwise from north, degrees), the polar stream a radar gives; :func:`read_plots_csv` reads it back
through ``immnet.data.csvio.read_plots_csv``, the reader of ``immnet track`` (docs/multi-target.md).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from immnet.data import adsb, radar
from immnet.data.geodesy import geodetic_to_enu
from immnet.data.scratch import check_writable, publishing
from immnet.data.spec import check_numbers

# the plot CSV is immnet track's: one reader of it, immnet.data.csvio's
from immnet.data.csvio import PLOT_COLUMNS as CSV_COLUMNS
from immnet.data.csvio import read_plots_csv as _read_plots

FORMAT = "scene"
FORMAT_VERSION = 1
TRAIN_SAMPLES = ("collections/quickstart",)
"""The samples whose scenes are for training and tuning; scenes of any other sample are for evaluation only."""
INDEX = "scenes.json"
SPLITS = ("train", "test")


@dataclass(frozen=True)
class SceneSpec:
    """Every parameter of ``immnet data scenes`` (stored in each scene's meta as ``spec``)."""

    duration: float = 300.0  # seconds per scene
    dt: float = 5.0  # scan interval (s), or its mean with dt_jitter
    dt_jitter: float = 0.5  # intervals U[dt - dt_jitter, dt + dt_jitter]
    pd: float = 0.9  # detection probability of an aircraft in cover
    clutter: float = 10.0  # mean clutter plots per scan (Poisson), uniform over the cover in range/azimuth/elevation
    sigma_range: float = 30.0  # m
    sigma_azimuth_deg: float = 0.15
    sigma_elevation_deg: float = 0.15
    max_range: float = 60_000.0  # slant range of the cover (m)
    min_range: float = 500.0  # nearest clutter (m)
    min_elevation: float = 0.0  # the radar's horizon (degrees)
    max_elevation: float = 30.0  # top of the clutter's cover (degrees)
    # ADS-B scenes
    min_targets: int = 5  # aircraft in cover at every scan of a window, at least ...
    max_targets: int = 14  # ... and at most
    truth_gap: float = 30.0  # a scan has an aircraft's truth only between fresh positions at most this far apart (s)
    # 3D-LAST scenes
    targets: int = 8
    crossing_pairs: int = 2
    close_pairs: int = 2
    crossing_miss: float = 150.0  # horizontal miss distance of a crossing, U[0, crossing_miss] (m)
    close_separation: tuple = (300.0, 1000.0)  # horizontal separation of a close pair (m)
    last_step: float = 0.1  # the 3D-LAST simulation's step (s); scans fall on it

    def __post_init__(self):
        check_numbers(self)
        radar.check_scan_interval(self.dt, self.dt_jitter)
        if not self.duration >= self.dt:
            raise ValueError(f"duration must be at least one scan interval ({self.dt:g} s), got {self.duration}")
        if not 0 < self.pd <= 1:
            raise ValueError(f"pd (detection probability) must be in (0, 1], got {self.pd}")
        if not self.clutter >= 0:
            raise ValueError(f"clutter (mean plots per scan) must be >= 0, got {self.clutter}")
        for name in ("sigma_range", "sigma_azimuth_deg", "sigma_elevation_deg", "max_range", "truth_gap",
                     "last_step"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0 <= self.min_range < self.max_range:
            raise ValueError(f"min_range must be in [0, max_range), got {self.min_range} (max_range {self.max_range})")
        if not -90 <= self.min_elevation < self.max_elevation <= 90:
            raise ValueError(f"elevations need -90 <= min_elevation < max_elevation <= 90 degrees, got "
                             f"{self.min_elevation}, {self.max_elevation}")
        if not 1 <= self.min_targets <= self.max_targets:
            raise ValueError(f"targets in cover need 1 <= min_targets <= max_targets, got {self.min_targets}, "
                             f"{self.max_targets}")
        if self.targets < 1 or self.crossing_pairs < 0 or self.close_pairs < 0 \
                or 2 * (self.crossing_pairs + self.close_pairs) > self.targets:
            raise ValueError(f"3D-LAST scenes need targets >= 2 (crossing_pairs + close_pairs) >= 0, got targets "
                             f"{self.targets}, crossing_pairs {self.crossing_pairs}, close_pairs {self.close_pairs}")
        lo, hi = self.close_separation if len(self.close_separation) == 2 else (-1, -1)
        if not 0 < lo <= hi:
            raise ValueError(f"close_separation must be LOW,HIGH with 0 < LOW <= HIGH (m), got {self.close_separation}")
        if not self.crossing_miss >= 0:
            raise ValueError(f"crossing_miss must be >= 0, got {self.crossing_miss}")
        if self.dt - self.dt_jitter < 2 * self.last_step:
            raise ValueError(f"last_step ({self.last_step:g} s) must be at most half the shortest scan interval "
                             f"({self.dt - self.dt_jitter:g} s)")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["close_separation"] = [float(v) for v in self.close_separation]
        return d


@dataclass
class Scene:
    """One scene (the module docstring's arrays); ``meta`` its JSON-able description."""

    t: np.ndarray
    plot_offsets: np.ndarray
    plots: np.ndarray
    plot_polar: np.ndarray
    plot_cov: np.ndarray
    plot_source: np.ndarray
    truth_offsets: np.ndarray
    truth_states: np.ndarray
    truth_id: np.ndarray
    aircraft: np.ndarray
    site: np.ndarray
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.t)

    @property
    def name(self) -> str:
        return self.meta.get("name", "")

    def scan(self, k: int) -> tuple[float, np.ndarray, np.ndarray]:
        """``(t, plots [N, 3] ENU, covariance [N, 3, 3])`` of scan ``k``: what a tracker reads."""
        a, b = self.plot_offsets[k], self.plot_offsets[k + 1]
        return float(self.t[k]), self.plots[a:b], self.plot_cov[a:b]

    def scans(self):
        """Every scan's ``(t, plots, covariance)`` in time order."""
        for k in range(len(self)):
            yield self.scan(k)

    def truth(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(positions [n, 3] ENU, aircraft indices [n])`` of the aircraft in cover at scan ``k`` (scoring only)."""
        a, b = self.truth_offsets[k], self.truth_offsets[k + 1]
        return self.truth_states[a:b][:, [0, 3, 6]], self.truth_id[a:b]

    def arrays(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "meta"}


# --- the radar ------------------------------------------------------------------------------------
def observe(states: np.ndarray, scans: np.ndarray, spec: SceneSpec, rng: np.random.Generator,
            aircraft, site, meta: dict) -> Scene:
    """The scene a radar at the origin of the ENU frame makes of ``states [A, S, 9]`` (NaN rows: no truth at that
    scan) at the times ``scans [S]``: per scan, an aircraft with truth in cover is detected with probability
    ``spec.pd`` (polar noise), Poisson clutter of mean ``spec.clutter`` is added, the plots shuffled (the module
    docstring). Draws, per scan in order: detections, noise, the clutter count and positions, the order."""
    A, S = states.shape[:2]
    s_rho, s_az, s_el = spec.sigma_range, math.radians(spec.sigma_azimuth_deg), math.radians(spec.sigma_elevation_deg)
    pos = states[..., [0, 3, 6]]
    inview = _in_cover(pos, np.isfinite(states).all(-1), spec)
    plots_polar, sources, truth_states, truth_ids = [], [], [], []
    lo_el, hi_el = math.radians(spec.min_elevation), math.radians(spec.max_elevation)
    for k in range(S):
        ids = np.flatnonzero(inview[:, k])
        truth_states.append(states[ids, k])
        truth_ids.append(ids)
        det = ids[rng.random(len(ids)) < spec.pd]
        rho, az, el = radar.polar(pos[det, k])
        noise = rng.standard_normal((len(det), 3)) * np.array([s_rho, s_az, s_el])
        p = np.stack([rho, az, el], -1) + noise
        p[:, 0] = np.abs(p[:, 0])  # a range is >= 0 (30 m noise at km ranges: never folds in practice)
        n_c = int(rng.poisson(spec.clutter))
        c = np.stack([rng.uniform(spec.min_range, spec.max_range, n_c), rng.uniform(0.0, 2 * np.pi, n_c),
                      rng.uniform(lo_el, hi_el, n_c)], -1)
        allp = np.concatenate([p, c])
        src = np.concatenate([det, np.full(n_c, -1)])
        order = rng.permutation(len(allp))
        plots_polar.append(allp[order])
        sources.append(src[order])
    plot_off, truth_off = (np.cumsum([0, *map(len, rows)], dtype=np.int64) for rows in (sources, truth_ids))
    polar_all = np.concatenate(plots_polar) if plots_polar else np.empty((0, 3))
    polar_all[:, 1] = np.mod(polar_all[:, 1], 2 * np.pi)
    enu = radar.from_polar(polar_all[:, 0], polar_all[:, 1], polar_all[:, 2])
    cov = radar.polar_covariance(polar_all[:, 0], polar_all[:, 1], polar_all[:, 2], s_rho, s_az, s_el)
    counts = {"scans": int(S), "aircraft": int(A), "plots": int(len(polar_all)),
              "detections": int(sum((s >= 0).sum() for s in sources)),
              "clutter": int(sum((s < 0).sum() for s in sources)), "truth": int(truth_off[-1]),
              "in_cover": [int(min(np.diff(truth_off))), int(max(np.diff(truth_off)))] if S else [0, 0]}
    return Scene(t=np.asarray(scans, np.float64), plot_offsets=plot_off, plots=enu,
                 plot_polar=polar_all, plot_cov=cov, plot_source=np.concatenate(sources).astype(np.int64),
                 truth_offsets=truth_off,
                 truth_states=np.concatenate(truth_states) if truth_states else np.empty((0, 9)),
                 truth_id=np.concatenate(truth_ids).astype(np.int64), aircraft=np.asarray(list(aircraft), dtype=str),
                 site=np.asarray(site, np.float64), meta={**meta, "counts": counts})


# --- ADS-B scenes ---------------------------------------------------------------------------------
def _interp_positions(flights: list[adsb.Flight], site, grid: np.ndarray, gap: float) -> np.ndarray:
    """Each flight's ENU position ``[F, G, 3]`` at the times ``grid``, linear between fresh positions at most
    ``gap`` apart (NaN elsewhere): a quick count of the aircraft in cover, for choosing windows."""
    out = np.full((len(flights), len(grid), 3), np.nan)
    for i, f in enumerate(flights):
        a, b = np.searchsorted(grid, f.t[0]), np.searchsorted(grid, f.t[-1], side="right")
        if b <= a:
            continue
        g = grid[a:b]
        enu = geodetic_to_enu(f.lat, f.lon, f.h, site)
        j = np.clip(np.searchsorted(f.t, g, side="right"), 1, len(f.t) - 1)
        ok = (f.t[j] - f.t[j - 1]) <= gap
        for ax in range(3):
            out[i, a:b, ax] = np.where(ok, np.interp(g, f.t, enu[:, ax]), np.nan)
    return out


def _in_cover(pos: np.ndarray, known: np.ndarray, spec: SceneSpec) -> np.ndarray:
    """Where a position ``pos [..., 3]`` is known (``known [...]``, else NaN) and in the radar's cover."""
    return known & radar.covered(np.where(known[..., None], pos, np.inf), spec.max_range, spec.min_elevation)


def _smoothed(flights: list[adsb.Flight], site, scans: np.ndarray, spec: SceneSpec) -> np.ndarray:
    """Truth ``[F, S, 9]`` of the flights at ``scans`` (NaN where a scan lies in a gap of more than ``truth_gap``),
    from the white-jerk RTS smoother over their fresh positions near the window (:mod:`immnet.data.real`)."""
    from immnet.data.real import RealSpec, _has_truth, _measurement_var, smooth_at_scans

    rs = RealSpec()
    pad = max(60.0, spec.truth_gap)
    tracks = []
    for f in flights:
        a = max(np.searchsorted(f.t, scans[0] - pad) - 1, 0)
        b = min(np.searchsorted(f.t, scans[-1] + pad, side="right") + 1, len(f.t))
        sub = adsb.Flight(f.id, f.icao24, f.t[a:b], f.lat[a:b], f.lon[a:b], f.h[a:b], f.exact_time[a:b])
        enu = geodetic_to_enu(sub.lat, sub.lon, sub.h, site)
        ok = _has_truth(sub.t, scans, spec.truth_gap)
        tracks.append((sub.t, enu, _measurement_var(sub, enu, rs), scans, scans[0], ok))
    return np.stack(smooth_at_scans(tracks, np.array([rs.q_h, rs.q_h, rs.q_v])))


def sample_flights(sample) -> tuple[list[adsb.Flight], Path]:
    """The flights of one sample (a name or a file) with ``.sample`` set, and the file."""
    path = adsb.resolve_sample(sample)
    return adsb.flights(adsb.read_records(path), sample=str(sample)).flights, path


def split_of(sample, train_samples=TRAIN_SAMPLES) -> str:
    """``train`` for a sample among ``train_samples`` (by name, or by being the same file), else ``test``."""
    if str(sample) in train_samples:
        return "train"
    path = _resolved(sample)
    return "train" if path is not None and any(_resolved(name) == path for name in train_samples) else "test"


def _resolved(sample) -> Path | None:
    """The resolved file of a sample (a name or a file), None where there is none."""
    try:
        return adsb.resolve_sample(sample).resolve()
    except FileNotFoundError:
        return None


def _stem(sample) -> str:
    s = str(sample)
    for suf in (*adsb.SUFFIXES, *adsb.CSV_SUFFIXES):
        s = s.removesuffix(suf)
    return Path(s).name.replace(" ", "_") or "sample"


def adsb_scenes(sample, n: int, spec: SceneSpec = SceneSpec(), seed: int = 0, site=None,
                flights: list[adsb.Flight] | None = None, split: str | None = None) -> list[Scene]:
    """Up to ``n`` scenes of one ADS-B sample, in windows of ``spec.duration`` that do not overlap in time and in
    which between ``spec.min_targets`` and ``spec.max_targets`` aircraft are in cover at every scan.

    Windows are found on a grid of ``dt`` seconds by linear interpolation of the fresh positions, tried in an
    order drawn from ``(seed, crc32(sample))``, and kept where the smoothed truth confirms the count at every scan.
    A ValueError where the sample has no such window."""
    if flights is None:
        flights, _ = sample_flights(sample)
    if not flights:
        raise ValueError(f"sample {sample}: no flights")
    if site is None:
        site = radar.median_site(np.concatenate([f.lat for f in flights]), np.concatenate([f.lon for f in flights]))
    site = tuple(float(v) for v in site)
    split = split or split_of(sample)
    t0 = min(f.t[0] for f in flights)
    t1 = max(f.t[-1] for f in flights)
    step = max(spec.dt, 10.0)
    grid = np.arange(t0, t1 + step, step)
    pos = _interp_positions(flights, site, grid, spec.truth_gap)
    count = _in_cover(pos, np.isfinite(pos).all(-1), spec).sum(0)
    w = int(math.ceil(spec.duration / step)) + 1
    if len(grid) < w:
        raise ValueError(f"sample {sample}: spans {t1 - t0:.0f} s, less than one scene of {spec.duration:g} s")
    win = np.lib.stride_tricks.sliding_window_view(count, w)
    ok = np.flatnonzero((win.min(1) >= spec.min_targets) & (win.max(1) <= spec.max_targets))
    if not len(ok):
        raise ValueError(f"sample {sample}: no window of {spec.duration:g} s with {spec.min_targets}-"
                         f"{spec.max_targets} aircraft in cover ({spec.max_range / 1000:g} km of site "
                         f"{site[0]:.4f},{site[1]:.4f}) at every moment; the count ranges over "
                         f"{int(count.min())}-{int(count.max())} (try --max-range, --site or --targets-in-cover)")
    order = np.random.default_rng([int(seed), zlib.crc32(str(sample).encode())]).permutation(ok)
    scenes, taken, tried = [], [], 0
    for i in order:
        if len(scenes) >= n:
            break
        start = float(grid[i])
        if any(abs(start - s) < spec.duration + spec.dt for s in taken):
            continue
        tried += 1
        rng = np.random.default_rng([int(seed), zlib.crc32(str(sample).encode()), int(math.floor(start))])
        scans = radar.scan_times(start, start + spec.duration, spec.dt, spec.dt_jitter, rng)
        near = [j for j in range(len(flights)) if np.isfinite(pos[j, i : i + w]).any()]
        # aircraft near the cover too: the smoother's truth decides who is in cover at each scan
        states = _smoothed([flights[j] for j in near], site, scans, spec)
        inview = _in_cover(states[..., [0, 3, 6]], np.isfinite(states).all(-1), spec)
        per_scan = inview.sum(0)
        if per_scan.min() < spec.min_targets or per_scan.max() > spec.max_targets:
            continue
        seen = inview.any(1)
        keep = [near[j] for j in np.flatnonzero(seen)]
        name = f"{_stem(sample)}-{len(scenes):02d}"
        meta = {"format": FORMAT, "version": FORMAT_VERSION, "kind": "adsb", "name": name, "split": split,
                "sample": str(sample), "seed": int(seed), "start": start, "site": list(site), "spec": spec.to_dict(),
                "samples_of_aircraft": sorted({flights[j].sample for j in keep})}
        scenes.append(observe(states[seen], scans, spec, rng, [flights[j].id for j in keep], site, meta))
        taken.append(start)
    if not scenes:
        raise ValueError(f"sample {sample}: none of {tried} candidate windows keeps {spec.min_targets}-"
                         f"{spec.max_targets} aircraft in cover at every scan of its smoothed truth")
    return scenes


# --- 3D-LAST scenes -------------------------------------------------------------------------------
def _heading(s: np.ndarray) -> float:
    return math.atan2(s[4], s[1])  # of velocity (vy, vx), counterclockwise from east


def _rotate_move(traj: np.ndarray, k: int, angle: float, to: np.ndarray) -> np.ndarray:
    """``traj [T, 9]`` rotated by ``angle`` (rad, about the vertical through its position at step ``k``) and moved so
    that position is ``to [3]``: velocities and accelerations rotate with it (the motion is unchanged)."""
    c, s = math.cos(angle), math.sin(angle)
    out = traj.copy()
    x, y = traj[:, 0:3].copy(), traj[:, 3:6].copy()  # east and north: position, velocity, acceleration
    x[:, 0] -= traj[k, 0]
    y[:, 0] -= traj[k, 3]
    out[:, 0:3], out[:, 3:6] = c * x - s * y, s * x + c * y
    out[:, [0, 3]] += to[:2]
    out[:, 6] += to[2] - traj[k, 6]
    return out


def last_scene(index: int, spec: SceneSpec = SceneSpec(), seed: int = 0, split: str = "test") -> Scene:
    """3D-LAST scene ``index``: ``spec.targets`` trajectories of the generator in one volume, with crossing and close
    pairs (the module docstring), seen by the radar at the origin."""
    from immnet import keys
    from immnet.data.generate import hashed_generator, simulate
    from immnet.data.spec import DataSpec

    step = spec.last_step
    T = int(round(spec.duration / step)) + 1
    min_seg = max(int(round(min(40.0, spec.duration / 3) / step)), 1)
    ds = DataSpec(T=T, dt=step, min_segment=min_seg)
    rng = np.random.default_rng([int(seed), 2, int(index)])
    scans = radar.scan_times(0.0, spec.duration, spec.dt, spec.dt_jitter, rng)
    k_of = np.round(scans / step).astype(np.int64)
    scans = k_of * step
    pool = []
    g = hashed_generator(f"scenes-3dlast:{int(seed)}:{int(index)}")
    for _ in range(8):  # batches of candidates until the pairs are placed
        td, bad = simulate(g, 4 * spec.targets, ds)
        pool += [s for s, b in zip(td[keys.STATES].numpy(), bad.numpy()) if not b]
        if len(pool) >= 2 * spec.targets:
            break

    def inside(tr):
        p = tr[k_of][:, [0, 3, 6]]
        return bool(radar.covered(p, spec.max_range, spec.min_elevation).all()
                    and (tr[:, 6] >= ds.hard_alt_min).all() and (tr[:, 6] <= ds.hard_alt_max).all())

    pool = [tr for tr in pool if inside(tr)]
    chosen, names = [], []
    pairs = ["crossing"] * spec.crossing_pairs + ["close"] * spec.close_pairs
    for p_i, kind in enumerate(pairs):
        if not pool:
            break
        a = pool.pop(0)
        kk = int(k_of[rng.integers(len(scans) // 4, max(3 * len(scans) // 4, len(scans) // 4 + 1))])
        ha = _heading(a[kk])
        if kind == "crossing":
            turn = rng.uniform(math.radians(30), math.radians(150)) * rng.choice([-1.0, 1.0])
            d = rng.uniform(0.0, spec.crossing_miss)
            off_dir = rng.uniform(0.0, 2 * np.pi)
            offset = np.array([d * math.cos(off_dir), d * math.sin(off_dir), rng.uniform(-50.0, 50.0)])
        else:
            turn = rng.uniform(-math.radians(10), math.radians(10))
            d = rng.uniform(*spec.close_separation) * rng.choice([-1.0, 1.0])
            offset = np.array([-d * math.sin(ha), d * math.cos(ha), rng.uniform(-100.0, 100.0)])
        for j, b in enumerate(pool):
            moved = _rotate_move(b, kk, ha + turn - _heading(b[kk]), a[kk, [0, 3, 6]] + offset)
            if inside(moved):
                pool.pop(j)
                chosen += [a, moved]
                names += [f"{kind}{p_i}a", f"{kind}{p_i}b"]
                break
        else:
            raise ValueError(f"3D-LAST scene {index}: no trajectory of {len(pool)} candidates could be placed as the "
                             f"{kind} partner of another inside the cover ({spec.max_range:g} m); raise max_range")
    while len(chosen) < spec.targets and pool:
        chosen.append(pool.pop(0))
        names.append(f"single{len(names)}")
    if len(chosen) < spec.targets:
        raise ValueError(f"3D-LAST scene {index}: only {len(chosen)} of {spec.targets} trajectories stay inside the "
                         f"cover ({spec.max_range:g} m); raise max_range")
    states = np.stack([c[k_of] for c in chosen])
    meta = {"format": FORMAT, "version": FORMAT_VERSION, "kind": "3d-last", "name": f"3dlast-{index:02d}",
            "split": split, "sample": "3d-last", "seed": int(seed), "index": int(index), "spec": spec.to_dict()}
    return observe(states, scans, spec, rng, names, [np.nan] * 3, meta)


# --- on disk --------------------------------------------------------------------------------------
_ARRAYS = {"t": (1, np.float64), "plot_offsets": (1, np.int64), "plots": (2, np.float64),
           "plot_polar": (2, np.float64), "plot_cov": (3, np.float64), "plot_source": (1, np.int64),
           "truth_offsets": (1, np.int64), "truth_states": (2, np.float64), "truth_id": (1, np.int64),
           "aircraft": (1, None), "site": (1, np.float64)}


def save_scene(scene: Scene, path) -> Path:
    """Write one scene as ``path`` (``.npz``), atomically."""
    path = Path(path)
    if path.suffix != ".npz":
        raise ValueError(f"{path}: a scene file must end in .npz")
    check_writable(path)
    with publishing(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, meta=np.asarray(json.dumps(scene.meta, allow_nan=False)), **scene.arrays())
    return path


def load_scene(path) -> Scene:
    """A scene file (:func:`save_scene`), read with ``allow_pickle=False``; a ValueError names what is wrong."""
    from immnet.data.storage import read_npz

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no scene file at {path}")
    arrays, names = read_npz(path, (*_ARRAYS, "meta"))
    missing = [k for k in (*_ARRAYS, "meta") if k not in names]
    if missing:
        raise ValueError(f"{path}: not a scene: the array(s) {', '.join(missing)} are missing (has {sorted(names)})")
    try:
        meta = json.loads(str(arrays.pop("meta")))
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not a readable scene file (its meta is not JSON: {err})") from None
    for k, (ndim, dtype) in _ARRAYS.items():
        a = arrays[k]
        if a.ndim != ndim or (dtype is not None and a.dtype != dtype) or (dtype is None and a.dtype.kind != "U"):
            raise ValueError(f"{path}: array {k!r} has shape {a.shape} and dtype {a.dtype}, expected {ndim} "
                             f"dimension(s) of {dtype.__name__ if dtype else 'text'}")
    S, P, Q = len(arrays["t"]), len(arrays["plots"]), len(arrays["truth_states"])
    for off, total, what in (("plot_offsets", P, "plots"), ("truth_offsets", Q, "truth_states")):
        o = arrays[off]
        if len(o) != S + 1 or o[0] != 0 or o[-1] != total or (np.diff(o) < 0).any():
            raise ValueError(f"{path}: {off} must be {S + 1} non-decreasing offsets from 0 to the {total} rows of {what}")
    shapes = {"plots": (P, 3), "plot_polar": (P, 3), "plot_cov": (P, 3, 3), "plot_source": (P,),
              "truth_states": (Q, 9), "truth_id": (Q,), "site": (3,)}
    for k, shape in shapes.items():
        if arrays[k].shape != shape:
            raise ValueError(f"{path}: array {k!r} has shape {arrays[k].shape}, expected {shape}")
    A = len(arrays["aircraft"])
    if ((arrays["truth_id"] < 0) | (arrays["truth_id"] >= A)).any() or \
            ((arrays["plot_source"] < -1) | (arrays["plot_source"] >= A)).any():
        raise ValueError(f"{path}: truth_id or plot_source names an aircraft outside 0..{A - 1} (-1: clutter)")
    if S > 1 and not (np.diff(arrays["t"]) > 0).all():
        raise ValueError(f"{path}: the scan times t are not strictly increasing")
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: meta is not a JSON object")
    return Scene(**arrays, meta=meta)


# --- plots as CSV ---------------------------------------------------------------------------------
def write_plots_csv(scene: Scene, path) -> Path:
    """The scene's plots as ``t,range,azimuth,elevation`` rows (s, m, degrees clockwise from north, degrees), scan
    by scan in the scene's (shuffled) order; a scan without plots is the row ``t,,,``; written atomically. Numbers are written to full precision (a
    float's shortest repr), so that reading gives the same values."""
    path = Path(path)
    check_writable(path)
    with publishing(path, suffix=".csv") as tmp, open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        deg = np.degrees(scene.plot_polar[:, 1:])
        for k in range(len(scene)):
            a, b = scene.plot_offsets[k], scene.plot_offsets[k + 1]
            if a == b:  # a scan without plots is a row of its time alone
                w.writerow([repr(float(scene.t[k])), "", "", ""])
            for i in range(a, b):
                w.writerow([repr(float(v)) for v in (scene.t[k], scene.plot_polar[i, 0], *deg[i])])
    return path


def read_plots_csv(path) -> list[tuple[float, np.ndarray]]:
    """``[(t, polar [N, 3])]`` per scan: range (m), azimuth and elevation (degrees), from a ``t,range,azimuth,elevation``
    CSV, read and checked by the one reader of plot CSVs, ``immnet.data.csvio.read_plots_csv`` (which ``immnet track``
    reads them with): rows of one ``t`` together, scans in time order, ``t,,,`` a scan without plots. A ValueError
    names the line that is wrong."""
    got = _read_plots(path, convert=False)
    if not got.polar:
        raise ValueError(f"{path}: the plots are x,y,z; a scene's are {','.join(CSV_COLUMNS)}")
    return [(float(t), got.given[a:b]) for t, a, b in zip(got.t, got.offsets[:-1], got.offsets[1:])]


# --- a set of scenes ------------------------------------------------------------------------------
def make_scenes(out, samples=(), n: int = 3, spec: SceneSpec = SceneSpec(), seed: int = 0, site=None,
                last: int = 0, last_split: str = "test", train_samples=TRAIN_SAMPLES, write_csv: bool = False,
                overwrite: bool = False, progress: bool = False) -> dict:
    """Write ``out/<split>/<name>.npz`` for up to ``n`` scenes of each ADS-B sample and ``last`` 3D-LAST scenes, and
    ``out/scenes.json`` (the index: every scene's name, split, file, kind, sample and counts, and the parameters);
    with ``write_csv`` also each scene's plots as ``out/<split>/<name>.csv`` (:func:`write_plots_csv`). The directory is written whole through a temporary sibling. Returns the index."""
    from immnet.data.storage import _check_out

    out = Path(out)
    if not samples and not last:
        raise ValueError("no scenes asked for: give ADS-B samples and/or a number of 3D-LAST scenes (--last)")
    if n < 1:
        raise ValueError(f"scenes per sample must be >= 1, got {n}")
    if last < 0:
        raise ValueError(f"the number of 3D-LAST scenes must be >= 0, got {last}")
    if last_split not in SPLITS:
        raise ValueError(f"last_split must be one of {', '.join(SPLITS)}, got {last_split!r}")
    _check_out(out, overwrite)
    check_writable(out, "folder")
    start = time.perf_counter()
    scenes = []
    for sample in samples:
        fl, path = sample_flights(sample)
        got = adsb_scenes(sample, n, spec, seed, site=site, flights=fl, split=split_of(sample, train_samples))
        for s in got:
            s.meta["sample_sha256"] = adsb.file_digest(path)
        scenes += got
        if progress:
            print(f"[scenes] {sample}: {len(got)} scene(s)", flush=True)
    scenes += [last_scene(i, spec, seed, split=last_split) for i in range(last)]
    index = {"format": FORMAT, "version": FORMAT_VERSION, "seed": int(seed), "spec": spec.to_dict(),
             "train_samples": list(train_samples), "scenes": []}
    with publishing(out) as tmp:
        tmp.mkdir()
        for s in scenes:
            rel = f"{s.meta['split']}/{s.name}.npz"
            save_scene(s, tmp / rel)
            if write_csv:
                write_plots_csv(s, (tmp / rel).with_suffix(".csv"))
            index["scenes"].append({"name": s.name, "file": rel, "split": s.meta["split"], "kind": s.meta["kind"],
                                    "sample": s.meta["sample"], "counts": s.meta["counts"]})
        index["seconds"] = round(time.perf_counter() - start, 2)
        (tmp / INDEX).write_text(json.dumps(index, indent=1, allow_nan=False) + "\n")
    return index


def load_index(directory) -> dict:
    """``scenes.json`` of a set written by :func:`make_scenes`."""
    from immnet.data.storage import read_json

    p = Path(directory) / INDEX
    if not p.is_file():
        raise FileNotFoundError(f"no scene set at {directory} (no {INDEX})")
    index = read_json(p)
    if not isinstance(index, dict) or index.get("format") != FORMAT or not isinstance(index.get("scenes"), list):
        raise ValueError(f"{p}: not the index of a scene set (format {FORMAT!r})")
    return index


def load_split(directory, split: str) -> list[Scene]:
    """Every scene of one split of a set, in the index's order."""
    directory = Path(directory)
    index = load_index(directory)
    return [load_scene(directory / e["file"]) for e in index["scenes"] if e["split"] == split]
