"""Scoring multi-target trackers on scenes (``immnet evaluate --data SCENES``; docs/evaluation.md, "Scenes").

A scene set (``immnet data scenes``) is scored per method, a method being the per-track filter of the multi-target
tracker (``immnet.filters.multi.MultiTargetTracker``; any model-based IMM or Kalman filter, or a shipped network, by
name: ``TrackFilter.by_name``). Three kinds of row:

* ``NAME``: the tracker with filter ``NAME`` on each scene's plots (clutter and missed detections included), its
  confirmed tracks at each scan being the estimates;
* ``NAME (told association)``: the same filter told the association (:func:`run_told`): each aircraft's own plots
  (the truth's ``plot_source``), no clutter, the same two-point start, coasting and deletion, its track reported
  from its start (no confirmation to wait for); what the tracker would reach if it never mistook a plot;
* ``raw plots``: no tracker, each scan's detections of the aircraft as the estimates.

Every row is scored the same way (:func:`score`): per scan, GOSPA (``immnet.evaluation.gospa``, cut-off ``c``, order
``p``, ``alpha``) between the positions of the aircraft in cover and the estimates, with its parts, and the identity
metrics (id switches, fragmentations, continuity) of ``track_metrics`` over the scene; time per scan is the wall time
of the tracker's ``step`` (the told reference's step: its predict and update).
"""

from __future__ import annotations

import math
import time

import numpy as np

TOLD = " (told association)"
RAW = "raw plots"


def clutter_density(spec: dict) -> float:
    """A scene's clutter plots per m^3: the Poisson mean over the volume of its cover (a spherical shell between
    ``min_range`` and ``max_range``, between the elevations ``min_elevation`` and ``max_elevation``)."""
    vol = (2 * math.pi / 3) * (spec["max_range"] ** 3 - spec["min_range"] ** 3) * (
        math.sin(math.radians(spec["max_elevation"])) - math.sin(math.radians(spec["min_elevation"])))
    return max(spec["clutter"], 1e-3) / vol


def cover(spec: dict):
    """A scene's radar cover (``immnet.filters.multi.Cover``): what a track beyond it has left."""
    from immnet.filters.multi import Cover

    return Cover(spec["max_range"], spec["min_elevation"])


SCENE_GIVEN = ("pd", "clutter_density")
"""The tracker's settings that ``run_tracker`` takes from each scene (its cover too), left out of a run's record."""


def recorded(tracker) -> dict:
    """What a run's record says the tracker ran with: its ``settings()`` but those each scene gives (``SCENE_GIVEN``;
    ``immnet evaluate``'s JSON and W&B config, ``benchmarks/mtt_peer.py``'s JSON)."""
    return {k: v for k, v in tracker.settings().items() if k not in SCENE_GIVEN}


def run_tracker(scene, filter: str, **settings) -> dict:
    """One scene through ``MultiTargetTracker(filter, **settings)``, told the scene's radar cover (``cover``), detection
    probability and clutter density (JPDA's; GNN reads neither): per scan the confirmed tracks' ids and positions,
    and the seconds of each ``step``."""
    from immnet.filters.multi import MultiTargetTracker

    spec = scene.meta["spec"]
    settings = {"cover": cover(spec), **settings}
    tracker = MultiTargetTracker(filter, pd=spec["pd"], clutter_density=clutter_density(spec), **settings)
    est_ids, est_pos, seconds = [], [], []
    for t, plots, cov in scene.scans():
        t0 = time.perf_counter()
        reports = tracker.step(t, plots, cov)
        seconds.append(time.perf_counter() - t0)
        est_ids.append(np.array([r.track_id for r in reports], dtype=np.int64))
        est_pos.append(np.array([r.state[[0, 3, 6]] for r in reports], dtype=np.float64).reshape(-1, 3))
    return {"est_ids": est_ids, "est_pos": est_pos, "seconds": seconds}


def run_told(scene, filter: str, delete_after: int | None = None, max_pos_std: float | None = None,
             init=None, min_coast: float | None = None) -> dict:
    """The filter ``filter`` told the association: one track per aircraft, stepped together (one batch, as the
    tracker's), on each aircraft's own plots alone (``plot_source``; clutter never reaches it). A track starts from
    its aircraft's first two plots (the tracker's two-point start ``init``, a ``TwoPointStart``, its default where
    None: a plot, then the aircraft's next plot, with the start's vertical-speed prior), is
    predicted to every scan, updated with its aircraft's plot where there is one (else it coasts), and deleted after
    ``delete_after`` consecutive scans without one spanning ``min_coast`` s since its last, at a scan without one
    outside the radar's cover, or once its position std exceeds ``max_pos_std`` (the tracker's defaults where None);
    its aircraft's next plot then seeds a new track. A track is reported at every scan from its start to its deletion,
    under its own id. Returns what :func:`run_tracker` returns."""
    from immnet.filters.multi import DELETE_AFTER, MAX_POS_STD, MIN_COAST, TrackFilter, TwoPointStart, kept

    delete_after = DELETE_AFTER if delete_after is None else int(delete_after)
    max_pos_std = MAX_POS_STD if max_pos_std is None else float(max_pos_std)
    min_coast = MIN_COAST if min_coast is None else float(min_coast)
    init = TwoPointStart() if init is None else init
    f = TrackFilter.by_name(filter)
    seen = cover(scene.meta["spec"])
    A = len(scene.aircraft)
    ac = np.zeros(0, np.int64)  # each track's aircraft (a track per row of the filter)
    ids = np.zeros(0, np.int64)
    misses = np.zeros(0, np.int64)
    last = np.zeros(0)  # each track's last plot's time (s)
    seed_z, seed_R, seed_t = np.full((A, 3), np.nan), np.zeros((A, 3, 3)), np.full(A, np.nan)
    next_id, t_prev = 0, None
    est_ids, est_pos, seconds = [], [], []
    for k in range(len(scene)):
        t, plots, cov = scene.scan(k)
        a, b = scene.plot_offsets[k], scene.plot_offsets[k + 1]
        src = scene.plot_source[a:b]
        t0 = time.perf_counter()
        mine = src >= 0
        plot_of = np.full(A, -1, np.int64)
        plot_of[src[mine]] = np.flatnonzero(mine)
        K = len(ids)
        if K:
            f.predict(t - t_prev)
            j = plot_of[ac]
            hit = j >= 0
            z = np.full((K, 3), np.nan)
            R = np.broadcast_to(np.eye(3), (K, 3, 3)).copy()
            z[hit], R[hit] = plots[j[hit]], cov[j[hit]]
            f.update(z, R)
            misses = np.where(hit, 0, misses + 1)
            last = np.where(hit, t, last)
            plot_of[ac[hit]] = -1  # taken by its track
            x, P = f.state()
            keep = kept(x, P, hit, misses, delete_after, max_pos_std, seen, t - last, min_coast)  # the tracker's rules
            if not keep.all():
                f.drop(keep)
                ids, misses, last, ac = ids[keep], misses[keep], last[keep], ac[keep]
        # plots of aircraft without a track: a second plot starts one, a first one seeds
        free = np.flatnonzero(plot_of >= 0)
        start = free[np.isfinite(seed_t[free])]
        if len(start):
            j = plot_of[start]
            f.start(plots[j], cov[j], seed_z[start], seed_R[start], t - seed_t[start], init.vz_std, init.p_cv)
            ac = np.concatenate([ac, start])
            ids = np.concatenate([ids, next_id + np.arange(len(start))])
            misses = np.concatenate([misses, np.zeros(len(start), np.int64)])
            last = np.concatenate([last, np.full(len(start), t)])
            next_id += len(start)
            seed_t[start] = np.nan
        first = free[~np.isin(free, start)]
        seed_z[first], seed_R[first], seed_t[first] = plots[plot_of[first]], cov[plot_of[first]], t
        x, _ = f.state()
        seconds.append(time.perf_counter() - t0)
        est_ids.append(ids.copy())
        est_pos.append(x[:, [0, 3, 6]].reshape(-1, 3))
        t_prev = t
    return {"est_ids": est_ids, "est_pos": est_pos, "seconds": seconds}


def raw_plots(scene) -> dict:
    """No tracker: each scan's detections of the aircraft (its plots that are not clutter), under the aircraft's
    index as the id."""
    ids, pos = [], []
    for k in range(len(scene)):
        a, b = scene.plot_offsets[k], scene.plot_offsets[k + 1]
        src = scene.plot_source[a:b]
        ids.append(src[src >= 0])
        pos.append(scene.plots[a:b][src >= 0])
    return {"est_ids": ids, "est_pos": pos, "seconds": [0.0] * len(scene)}


def score(scene, run: dict, c: float = 200.0, p: float = 2.0, alpha: float = 2.0) -> dict:
    """One scene's scores of a run (:func:`run_tracker`'s dict): ``track_metrics``' GOSPA means and identity metrics,
    ``gospa_per_scan`` (and its parts per scan), ``t`` (the scan times from the scene's first, s), the time per scan
    (``ms_per_scan`` median, mean and max), and ``over_interval``: the scans whose time exceeds the interval to the
    next scan (the last scan: the scene's shortest interval)."""
    from immnet.evaluation.gospa import track_metrics

    truth = [scene.truth(k) for k in range(len(scene))]
    m = track_metrics([tr[1] for tr in truth], [tr[0] for tr in truth], run["est_ids"], run["est_pos"], c, p, alpha)
    per = m.pop("per_scan")
    m.pop("per_truth")
    sec = np.asarray(run["seconds"], dtype=np.float64)
    gaps = np.diff(scene.t)
    interval = np.append(gaps, gaps.min() if len(gaps) else np.inf)
    return {**m, "scans": len(scene),
            **{f"{k}_per_scan": [float(g[k]) for g in per] for k in ("gospa", "localisation", "missed", "false")},
            "t": (scene.t - scene.t[0]).tolist(),
            "ms_per_scan": {"median": float(np.median(sec) * 1e3), "mean": float(sec.mean() * 1e3),
                            "max": float(sec.max() * 1e3)},
            "over_interval": int((sec > interval).sum()), "min_interval": float(interval.min())}


def combine(rows: list[dict]) -> dict:
    """A method's scores over scenes: GOSPA and its parts the mean over every scan of every scene (scenes weighted by
    their scans), id switches and fragmentations summed, continuity and coverage the means over scenes, the time per
    scan over every scan (median and mean of the scenes' medians and means weighted by scans, the max of maxima)."""
    n = np.array([r["scans"] for r in rows], dtype=np.float64)
    out = {k: float(np.mean(np.concatenate([r[f"{k}_per_scan"] for r in rows]))) for k in
           ("gospa", "localisation", "missed", "false")}
    out |= {k: int(sum(r[k] for r in rows)) for k in ("id_switches", "fragmentations")}
    out |= {k: float(np.mean([r[k] for r in rows])) for k in ("continuity", "coverage")}
    ms = {k: float(np.average([r["ms_per_scan"][k] for r in rows], weights=n)) for k in ("median", "mean")}
    ms["max"] = float(max(r["ms_per_scan"]["max"] for r in rows))
    return out | {"scans": int(n.sum()), "ms_per_scan": ms, "over_interval": int(sum(r["over_interval"] for r in rows)),
                  "min_interval": float(min(r["min_interval"] for r in rows))}


def evaluate_scenes(scenes: list, filters: list[str], told: bool = True, raw: bool = True, settings: dict | None = None,
                    c: float = 200.0, p: float = 2.0, alpha: float = 2.0, note=None) -> dict:
    """``{row: {"mean": combine(...), "scenes": {scene name: score(...)}}}`` for each filter (the tracker with
    ``settings``), its told-association reference where ``told`` (the same ``delete_after``, ``max_pos_std``,
    ``min_coast`` and ``init``), and the raw plots where ``raw``; every row runs on one scene before the next scene (the same machine
    state for each)."""
    settings = dict(settings or {})
    names = [name for f in filters for name in ((f, f + TOLD) if told else (f,))] + ([RAW] if raw else [])
    per = {n: {} for n in names}
    for sc in scenes:
        for f in filters:
            per[f][sc.name] = score(sc, run_tracker(sc, f, **settings), c, p, alpha)
            if told:
                told_run = run_told(sc, f, settings.get("delete_after"), settings.get("max_pos_std"),
                                    settings.get("init"), settings.get("min_coast"))
                per[f + TOLD][sc.name] = score(sc, told_run, c, p, alpha)
            if note:
                note(f"[{sc.name}] {f}: GOSPA {per[f][sc.name]['gospa']:.1f} m, "
                     f"{per[f][sc.name]['ms_per_scan']['median']:.1f} ms per scan")
        if raw:
            per[RAW][sc.name] = score(sc, raw_plots(sc), c, p, alpha)
    return {n: {"mean": combine(list(rows.values())), "scenes": rows} for n, rows in per.items()}


def tracker_gospa(scenes: list, make_filter, **settings) -> float:
    """The mean GOSPA (``combine``'s) of ``MultiTargetTracker(make_filter(), **settings)`` over ``scenes``, a fresh
    filter for each scene: what ``immnet tune --scenes`` minimizes."""
    return combine([score(sc, run_tracker(sc, make_filter(), **settings)) for sc in scenes])["gospa"]


SCALARS = ("gospa", "localisation", "missed", "false", "id_switches", "fragmentations", "continuity")
"""A method's scores over scenes that are one number each (``combine``): the table's columns after the method's name,
before the time per scan."""
COLUMNS = ["method", "GOSPA [m]", "localisation [m^2]", "missed [m^2]", "false [m^2]", "id switches",
           "fragmentations", "continuity", "ms per scan (median)", "ms per scan (max)"]


def table_rows(results: dict) -> list[list]:
    """One row per method: ``COLUMNS``' numbers from each method's ``mean``."""
    return [[name, *(r["mean"][k] for k in SCALARS), *(r["mean"]["ms_per_scan"][k] for k in ("median", "max"))]
            for name, r in results.items()]


def format_table(results: dict, markdown: bool = False) -> str:
    """The table of ``results`` (text, or Markdown)."""
    from immnet.evaluation.table import markdown_table, text_table

    fmt = ("{}", "{:.1f}", "{:.0f}", "{:.0f}", "{:.0f}", "{}", "{}", "{:.3f}", "{:.2f}", "{:.2f}")
    rows = [[f.format(v) for f, v in zip(fmt, row)] for row in table_rows(results)]
    return markdown_table(COLUMNS, rows, "|" + "---|" * len(COLUMNS)) if markdown else text_table(COLUMNS, rows)
