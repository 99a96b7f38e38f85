"""The multi-target peer: Stone Soup's GNN and JPDA trackers on the scenes of ``immnet data scenes``, tuned on the
training scenes only, against ours (``immnet.filters.multi.MultiTargetTracker``, where importable) in the same run.

Run (Stone Soup is in the ``dev`` extra, the tests' peer: ``pip install -e '.[dev]'``)::

    immnet data scenes --samples collections/quickstart collections/switzerland --out data/scenes --n 3
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/mtt_peer.py --scenes data/scenes [--tune-scenes 2] \\
        [--trackers gnn,jpda,ours,told] [--filter NAME[,NAME...]] [--split test|train] [--params OUT.json] \\
        [--time-limit S] [--out results/mtt_peer] [--write-benchmarks]

Stone Soup 1.9.1, as its documentation's examples build them: an extended Kalman filter (``ExtendedKalmanPredictor``,
``ExtendedKalmanUpdater``) with a nearly-constant-velocity model per axis (``ConstantVelocity``, noise diffusion
``q`` m^2/s^3) and the radar's polar model (``CartesianToElevationBearingRange``: elevation, bearing
counterclockwise from east, range; the scene's noise); each detection in polar coordinates as the radar gives it.

* GNN: ``GNNWith2DAssignment`` over ``DistanceHypothesiser`` with the ``Mahalanobis`` measure, gated at
  ``missed_distance`` (Mahalanobis units), in a ``MultiTargetTracker``;
* JPDA: ``JPDA`` over ``PDAHypothesiser`` (detection probability and clutter density of the scenes: the Poisson mean
  over the cover's volume in elevation-bearing-range, gate probability 0.9999), in a ``MultiTargetMixtureTracker``;
* both: ``MultiMeasurementInitiator`` (a ``SimpleMeasurementInitiator`` from each plot left over with a prior of
  zero velocity, ``init_speed`` m/s std per axis; tentative tracks associated by GNN; ``min_points`` updates confirm;
  tentative tracks deleted after ``tentative_steps`` scans without an update), and an ``UpdateTimeStepsDeleter``
  (``delete_steps`` scans without an update).

Tuning (training scenes only, the first ``--tune-scenes`` of split ``train``, of ``--tune-set`` where given): the grid
``GRID`` over ``q``, ``delete_steps`` and ``min_points``; the choice is the lowest mean GOSPA over the scans of those
scenes. The chosen settings then run on every ``test`` scene (``--split train``: on the training scenes instead, to
choose among our filters there; the table then holds no held-out number). Ours runs with its defaults (tuned on
training scenes by ``benchmarks/mtt_tune.py``; ``--filter`` another per-track filter, or several, comma-separated: a
row each, e.g. ``--filter real-imm-5s,radar-5s`` for the model-based IMM of 5 s scans beside a network), told the
scenes' detection probability and clutter density (nothing of it tuned on the test scenes).

References told the association (``--trackers ... told``): ours (``immnet.evaluation.scenes.run_told``: our filter on
each aircraft's own plots, its two-point start, coasting and deletion) and Stone Soup's EKF with the CV model (the
settings of its better tuned tracker: one track per aircraft from its first plot, updated with its aircraft's plots,
deleted after ``delete_steps`` scans without one); neither sees clutter.

``--time-limit S`` stops each Stone Soup run of a scene after S seconds of wall time (a SIGALRM timer, Stone Soup's
imports done before): the scans it finished are scored, the table says how many of the scene's scans were done.

Scoring, per scan: GOSPA (c = 200 m, p = 2, alpha = 2) between the positions of the aircraft in cover and the
positions of the tracks a tracker reports at that scan (Stone Soup: its tracks, confirmed by construction; ours:
the confirmed ``TrackReport``s), with its parts (Stone Soup's p-th power sums) and the identity metrics
(``immnet.evaluation.gospa.track_metrics``, held to Stone Soup's ``GOSPAMetric`` by the tests).
Time: the wall time of each scan's update (detections built outside it), its median and max over the scans, and the
scans whose update took longer than the interval to the next scan.

It writes OUT.json (every row, the grid, the choice) and OUT.md (the table); ``--write-benchmarks`` rewrites the
``## Multi-target trackers on scenes`` section of BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine, write_section  # noqa: E402

from immnet.data.scenes import Scene, load_index, load_scene  # noqa: E402
from immnet.evaluation.scenes import raw_plots  # noqa: E402

C, P, ALPHA = 200.0, 2.0, 2.0
GRID = {"q": (0.5, 5.0, 50.0), "delete_steps": (2, 3, 5), "min_points": (2, 3, 4)}
"""The tuning grid of both Stone Soup trackers."""
FIXED = {"missed_distance": 4.0, "init_speed": 300.0, "tentative_steps": 2, "prob_gate": 0.9999}
EPOCH = datetime.datetime(1970, 1, 1)
RAW = "raw plots of the aircraft (no tracker)"


# --- scoring: the one place that computes GOSPA ---------------------------------------------------------------------
def score(truth_ids: list, truth_pos: list, est_ids: list, est_pos: list) -> dict:
    """GOSPA per scan (means over the scans) and the identity metrics (``immnet.evaluation.gospa.track_metrics``)."""
    from immnet.evaluation.gospa import track_metrics

    m = track_metrics(truth_ids, truth_pos, est_ids, est_pos, c=C, p=P, alpha=ALPHA)
    per = m.pop("per_scan")
    m.pop("per_truth", None)
    return {**m, "gospa_per_scan": [float(g["gospa"]) for g in per]}


# --- Stone Soup -----------------------------------------------------------------------------------------------------
def clutter_density(scene: Scene) -> float:
    """The scene's clutter plots per unit of elevation (rad) x bearing (rad) x range (m): Poisson mean over the cover."""
    s = scene.meta["spec"]
    vol = math.radians(s["max_elevation"] - s["min_elevation"]) * 2 * math.pi * (s["max_range"] - s["min_range"])
    return s["clutter"] / vol


def outside(seen, state) -> bool:
    """Whether a Stone Soup state's position lies outside the radar's cover ``seen`` (``immnet.filters.multi.Cover``,
    ``immnet.evaluation.scenes.cover``)."""
    return not bool(seen.contains(np.asarray(state.state_vector, float).ravel()[[0, 2, 4]]))


def in_cover(scene: Scene, deleter):
    """``deleter``, and also a track that got no plot at a scan while its estimate lies outside the radar's cover:
    the rule our tracker applies (``MultiTargetTracker(cover=...)``), given to Stone Soup alike."""
    from stonesoup.deleter.base import Deleter
    from stonesoup.deleter.multi import CompositeDeleter
    from stonesoup.types.update import Update

    from immnet.evaluation.scenes import cover

    seen = cover(scene.meta["spec"])

    class OutOfCover(Deleter):
        def check_for_deletion(self, track, **kwargs):
            return not isinstance(track.state, Update) and outside(seen, track.state)

    return CompositeDeleter([deleter, OutOfCover()], intersect=False)


def stonesoup_tracker(kind: str, scene: Scene, q: float, delete_steps: int, min_points: int, missed_distance: float,
                      init_speed: float, tentative_steps: int, prob_gate: float):
    """A Stone Soup GNN or JPDA tracker for the scene's radar (module doc), and its measurement model."""
    from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
    from stonesoup.dataassociator.probability import JPDA
    from stonesoup.deleter.time import UpdateTimeStepsDeleter
    from stonesoup.hypothesiser.distance import DistanceHypothesiser
    from stonesoup.hypothesiser.probability import PDAHypothesiser
    from stonesoup.initiator.simple import MultiMeasurementInitiator
    from stonesoup.measures import Mahalanobis
    from stonesoup.models.measurement.nonlinear import CartesianToElevationBearingRange
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity
    from stonesoup.predictor.kalman import ExtendedKalmanPredictor
    from stonesoup.tracker.simple import MultiTargetMixtureTracker, MultiTargetTracker
    from stonesoup.types.array import CovarianceMatrix, StateVector
    from stonesoup.types.state import GaussianState
    from stonesoup.updater.kalman import ExtendedKalmanUpdater

    s = scene.meta["spec"]
    noise = np.diag([math.radians(s["sigma_elevation_deg"]) ** 2, math.radians(s["sigma_azimuth_deg"]) ** 2,
                     s["sigma_range"] ** 2])
    mm = CartesianToElevationBearingRange(ndim_state=6, mapping=(0, 2, 4), noise_covar=CovarianceMatrix(noise))
    tm = CombinedLinearGaussianTransitionModel([ConstantVelocity(q)] * 3)
    predictor = ExtendedKalmanPredictor(tm)
    updater = ExtendedKalmanUpdater(mm)
    gnn_hyp = DistanceHypothesiser(predictor, updater, measure=Mahalanobis(), missed_distance=missed_distance)
    prior = GaussianState(StateVector(np.zeros(6)), CovarianceMatrix(np.diag([0.0, init_speed ** 2] * 3)))
    initiator = MultiMeasurementInitiator(prior_state=prior, measurement_model=mm,
                                          deleter=in_cover(scene, UpdateTimeStepsDeleter(tentative_steps)),
                                          data_associator=GNNWith2DAssignment(gnn_hyp), updater=updater,
                                          min_points=min_points)
    deleter = in_cover(scene, UpdateTimeStepsDeleter(delete_steps))
    if kind == "gnn":
        return MultiTargetTracker(initiator=initiator, deleter=deleter, detector=None,
                                  data_associator=GNNWith2DAssignment(gnn_hyp), updater=updater), mm
    pda = PDAHypothesiser(predictor, updater, clutter_spatial_density=clutter_density(scene), prob_detect=s["pd"],
                          prob_gate=prob_gate)
    return MultiTargetMixtureTracker(initiator=initiator, deleter=deleter, detector=None,
                                     data_associator=JPDA(pda), updater=updater), mm


def run_stonesoup(kind: str, scene: Scene, params: dict, out: dict | None = None) -> dict:
    """One scene through a Stone Soup tracker: per scan its tracks' positions and ids, and the seconds of each update
    (appended to ``out``'s lists scan by scan, so that a run stopped at a time limit keeps the scans it finished)."""
    from stonesoup.types.angle import Bearing, Elevation
    from stonesoup.types.array import StateVector
    from stonesoup.types.detection import Detection

    tracker, mm = stonesoup_tracker(kind, scene, **params)
    out = {"est_ids": [], "est_pos": [], "seconds": []} if out is None else out
    est_ids, est_pos, seconds, number = out["est_ids"], out["est_pos"], out["seconds"], {}  # ids numbered by birth
    for k in range(len(scene)):
        a, b = scene.plot_offsets[k], scene.plot_offsets[k + 1]
        when = EPOCH + datetime.timedelta(seconds=float(scene.t[k]))
        dets = set()
        for rho, az, el in scene.plot_polar[a:b]:
            bearing = math.atan2(math.cos(az), math.sin(az))  # azimuth clockwise from north -> counterclockwise from east
            dets.add(Detection(StateVector([Elevation(el), Bearing(bearing), rho]), timestamp=when,
                               measurement_model=mm))
        t0 = time.perf_counter()
        _, tracks = tracker.update_tracker(when, dets)
        took = time.perf_counter() - t0
        tracks = sorted(tracks, key=lambda tr: tr.id)
        est_ids.append(np.array([number.setdefault(tr.id, len(number)) for tr in tracks], dtype=np.int64))
        est_pos.append(np.array([np.asarray(tr.state_vector, float).ravel()[[0, 2, 4]] for tr in tracks]).reshape(-1, 3))
        seconds.append(took)  # the update's seconds, appended last: a scan counts once its estimates are in
    return out


# --- ours -----------------------------------------------------------------------------------------------------------
def run_ours(scene: Scene, filter: str | None = None, associator: str = "gnn") -> dict:
    """Our ``MultiTargetTracker`` with its defaults (the settings tuned on training scenes: benchmarks/mtt_tune.py),
    ``filter`` the per-track filter (None: the default), told the scene's Pd and clutter density."""
    from immnet.evaluation.scenes import run_tracker
    from immnet.filters.multi import DEFAULT_FILTER

    filter = filter or DEFAULT_FILTER
    return run_tracker(scene, filter, associator=associator)


def run_ours_told(scene: Scene, filter: str | None = None) -> dict:
    """Our per-track filter told the association (``immnet.evaluation.scenes.run_told``)."""
    from immnet.evaluation.scenes import run_told
    from immnet.filters.multi import DEFAULT_FILTER

    filter = filter or DEFAULT_FILTER
    return run_told(scene, filter)


def run_stonesoup_told(scene: Scene, params: dict) -> dict:
    """Stone Soup's EKF with the nearly-constant-velocity model (the tuned ``q``) told the association: per aircraft a
    track started by ``SimpleMeasurementInitiator`` from its first plot (zero-velocity prior, ``init_speed`` std), then
    predicted to every scan and updated with its aircraft's plot (``SingleHypothesis``) where there is one; deleted
    after ``delete_steps`` scans without one, or at a scan without one outside the radar's cover (its next plot starts
    a new track); reported from its start."""
    from stonesoup.initiator.simple import SimpleMeasurementInitiator
    from stonesoup.types.angle import Bearing, Elevation
    from stonesoup.types.array import CovarianceMatrix, StateVector
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.state import GaussianState

    from immnet.evaluation.scenes import cover

    tracker, mm = stonesoup_tracker("gnn", scene, **params)
    predictor, updater = tracker.data_associator.hypothesiser.predictor, tracker.updater
    seen = cover(scene.meta["spec"])
    prior = GaussianState(StateVector(np.zeros(6)), CovarianceMatrix(np.diag([0.0, params["init_speed"] ** 2] * 3)))
    initiator = SimpleMeasurementInitiator(prior_state=prior, measurement_model=mm)
    tracks, misses, ids, next_id = {}, {}, {}, 0
    est_ids, est_pos, seconds = [], [], []
    for k in range(len(scene)):
        a, b = scene.plot_offsets[k], scene.plot_offsets[k + 1]
        when = EPOCH + datetime.timedelta(seconds=float(scene.t[k]))
        t0 = time.perf_counter()
        plot_of = {}
        for (rho, az, el), src in zip(scene.plot_polar[a:b], scene.plot_source[a:b]):
            if src >= 0:
                bearing = math.atan2(math.cos(az), math.sin(az))
                plot_of[int(src)] = Detection(StateVector([Elevation(el), Bearing(bearing), rho]), timestamp=when,
                                              measurement_model=mm)
        for ac in list(tracks):
            pred = predictor.predict(tracks[ac][-1], timestamp=when)
            if ac in plot_of:
                tracks[ac].append(updater.update(SingleHypothesis(pred, plot_of.pop(ac))))
                misses[ac] = 0
            else:
                tracks[ac].append(pred)
                misses[ac] += 1
                if misses[ac] >= params["delete_steps"] or outside(seen, pred):
                    del tracks[ac], misses[ac], ids[ac]
        for ac, det in plot_of.items():
            tracks[ac] = next(iter(initiator.initiate({det}, when)))
            misses[ac], ids[ac] = 0, next_id
            next_id += 1
        seconds.append(time.perf_counter() - t0)
        est_ids.append(np.array([ids[ac] for ac in tracks], dtype=np.int64))
        est_pos.append(np.array([np.asarray(tr.state_vector, float).ravel()[[0, 2, 4]] for tr in tracks.values()])
                       .reshape(-1, 3))
    return {"est_ids": est_ids, "est_pos": est_pos, "seconds": seconds}


class TimeLimit(Exception):
    """A run stopped at its wall-clock cap."""


def capped(fn, limit: float | None):
    """``fn()`` stopped after ``limit`` seconds of wall time (a SIGALRM timer; None: no cap). Returns ``(result,
    finished)``; a stopped run's result is None."""
    import signal

    if not limit:
        return fn(), True

    def stop(signum, frame):
        raise TimeLimit

    old = signal.signal(signal.SIGALRM, stop)
    signal.setitimer(signal.ITIMER_REAL, float(limit))
    try:
        return fn(), True
    except TimeLimit:
        return None, False
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, old)


# --- the run --------------------------------------------------------------------------------------------------------
def evaluate(run: dict, scene: Scene) -> dict:
    """The scores of a run over the scans it finished (all, unless it was stopped at a time limit)."""
    n = len(run["seconds"])
    tid = [scene.truth(k)[1] for k in range(n)]
    tpos = [scene.truth(k)[0] for k in range(n)]
    m = score(tid, tpos, run["est_ids"][:n], run["est_pos"][:n]) if n else {"gospa": float("nan"),
                                                                           "gospa_per_scan": []}
    sec = np.asarray(run["seconds"]) if n else np.full(1, np.nan)
    gaps = np.diff(scene.t)
    interval = np.append(gaps, gaps.min())[:n]
    return {**m, "ms_per_scan_median": float(np.median(sec) * 1e3), "ms_per_scan_mean": float(sec.mean() * 1e3),
            "ms_per_scan_max": float(sec.max() * 1e3), "over_interval": int((sec[:n] > interval).sum()),
            "scans": len(scene), "scans_done": n}


def mean_rows(rows: list[dict]) -> dict:
    keys = ("gospa", "localisation", "missed", "false", "ms_per_scan_median", "ms_per_scan_mean")
    out = {"scans": int(sum(r["scans"] for r in rows)), "scans_done": int(sum(r["scans_done"] for r in rows)),
           "ms_per_scan_max": float(max(r["ms_per_scan_max"] for r in rows)),
           "over_interval": int(sum(r["over_interval"] for r in rows))}
    rows = [r for r in rows if r["scans_done"]]  # a run stopped before its first scan has nothing to score
    if not rows:
        return out
    for k in keys:
        out[k] = float(np.mean([r[k] for r in rows if k in r]))
    # GOSPA over all scans together (scenes weighted by their scans)
    out["gospa_all_scans"] = float(np.mean(np.concatenate([r["gospa_per_scan"] for r in rows])))
    for k in ("id_switches", "fragmentations"):
        if all(k in r for r in rows):
            out[k] = int(sum(r[k] for r in rows))
    if all("continuity" in r for r in rows):
        out["continuity"] = float(np.mean([r["continuity"] for r in rows]))
    return out


def tune(kind: str, scenes: list[Scene], log, done: list | None = None) -> tuple[dict, list]:
    """The grid's points on the training scenes, the lowest mean GOSPA chosen; ``done``: points already scored on the
    same scenes (a previous OUT.json's), kept and not run again."""
    grid = []
    for q, ds, mp in itertools.product(GRID["q"], GRID["delete_steps"], GRID["min_points"]):
        old = [r for r in done or [] if (r["q"], r["delete_steps"], r["min_points"]) == (q, ds, mp)]
        if old:
            grid.append(old[0])
            continue
        params = {**FIXED, "q": q, "delete_steps": ds, "min_points": mp}
        rows = [evaluate(run_stonesoup(kind, sc, params), sc) for sc in scenes]
        g = float(np.mean(np.concatenate([r["gospa_per_scan"] for r in rows])))
        grid.append({"q": q, "delete_steps": ds, "min_points": mp, "gospa": g,
                     "ms_per_scan_median": float(np.mean([r["ms_per_scan_median"] for r in rows]))})
        log(f"[tune {kind}] q={q:g} delete_steps={ds} min_points={mp}: GOSPA {g:.1f} m")
    best = min(grid, key=lambda r: r["gospa"])
    return {**FIXED, "q": best["q"], "delete_steps": best["delete_steps"], "min_points": best["min_points"]}, grid


def table(result: dict) -> str:
    lines = ["| tracker | mean GOSPA (m) | localisation | missed | false | id switches | fragmentations | continuity | "
             "ms per scan (median) | ms per scan (max) | scans over the interval | scans done |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    f = lambda m, k, spec: format(m[k], spec) if k in m else "n/a"  # noqa: E731
    for name, m in result["test"].items():
        lines.append(f"| {name} | {f(m, 'gospa', '.1f')} | {f(m, 'localisation', '.0f')} | {f(m, 'missed', '.0f')} | "
                     f"{f(m, 'false', '.0f')} | {m.get('id_switches', 'n/a')} | {m.get('fragmentations', 'n/a')} | "
                     f"{f(m, 'continuity', '.3f')} | {f(m, 'ms_per_scan_median', '.1f')} | "
                     f"{f(m, 'ms_per_scan_max', '.1f')} | {m['over_interval']} | {m['scans_done']}/{m['scans']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", required=True, type=Path, help="a scene set of `immnet data scenes`")
    ap.add_argument("--tune-set", type=Path, default=None,
                    help="take the training scenes from this scene set instead (e.g. 3D-LAST scenes made with "
                         "--last-split train and another --seed)")
    ap.add_argument("--tune-scenes", type=int, default=2, help="training scenes to tune on (default 2)")
    ap.add_argument("--test-scenes", type=int, default=3, help="test scenes to evaluate on (default 3)")
    ap.add_argument("--trackers", default="gnn,jpda,ours,told",
                    help="of gnn, jpda, ours, told (ours and Stone Soup's EKF told the association), default all")
    ap.add_argument("--filter", default=None,
                    help="our per-track filter, or several comma-separated, a row each (a method's or a shipped "
                         "network's name; default: the tracker's default)")
    ap.add_argument("--split", choices=("test", "train"), default="test",
                    help="the scenes to evaluate on (default test; train: to choose among filters on training scenes)")
    ap.add_argument("--time-limit", type=float, default=None, metavar="S",
                    help="stop each Stone Soup run of a scene after S seconds of wall time; the scans it finished are "
                         "scored and the table says how many (default: no limit)")
    ap.add_argument("--params", type=Path, default=None,
                    help="a previous OUT.json of the same training scenes: its grid points are kept, the others scored")
    ap.add_argument("--out", type=Path, default=Path("results/mtt_peer"), help="OUT.json and OUT.md")
    ap.add_argument("--write-benchmarks", action="store_true", help="rewrite the section of BENCHMARKS.md")
    ap.add_argument("--quiet", action="store_true")
    a = ap.parse_args(argv)
    trackers = [t.strip() for t in a.trackers.split(",") if t.strip()]
    unknown = set(trackers) - {"gnn", "jpda", "ours", "told"}
    if unknown:
        ap.error(f"--trackers: unknown {', '.join(sorted(unknown))} (gnn, jpda, ours, told)")

    def log(msg):
        if not a.quiet:
            print(msg, file=sys.stderr, flush=True)

    index = load_index(a.scenes)
    entries = {s: [e for e in index["scenes"] if e["split"] == s] for s in ("train", "test")}
    tune_set = a.tune_set or a.scenes
    train = [load_scene(tune_set / e["file"]) for e in load_index(tune_set)["scenes"]
             if e["split"] == "train"][: a.tune_scenes]
    test = [load_scene(a.scenes / e["file"]) for e in entries[a.split][: a.test_scenes]]
    filters = [f.strip() for f in (a.filter or "").split(",") if f.strip()] or [None]
    if not test or (not train and a.params is None and ({"gnn", "jpda"} & set(trackers))):
        ap.error(f"{a.scenes}: needs test scenes and, to tune, training scenes (has {len(train)} train, "
                 f"{len(test)} test)")
    result = {"machine": machine(), "scenes": str(a.scenes), "train": [s.name for s in train],
              "test": {}, "test_scenes": [s.name for s in test], "grid": GRID, "fixed": FIXED, "tuning": {},
              "chosen": {}, "per_scene": {}}
    previous = json.loads(a.params.read_text()) if a.params else None
    for kind in ("gnn", "jpda"):
        if kind not in trackers:
            continue
        done = (previous or {}).get("tuning", {}).get(kind, [])
        if previous is not None and previous.get("train") not in (None, result["train"]):
            ap.error(f"--params {a.params}: tuned on {previous['train']}, these training scenes are {result['train']}")
        if previous is not None and kind in previous.get("chosen", {}) and not done:
            result["chosen"][kind], result["tuning"][kind] = previous["chosen"][kind], []
        else:  # the grid's points the previous run did not score are scored now
            result["chosen"][kind], result["tuning"][kind] = tune(kind, train, log, done)
        log(f"[{kind}] chosen {result['chosen'][kind]}")
    names = {"gnn": "Stone Soup GNN (EKF, CV)", "jpda": "Stone Soup JPDA (EKF, CV)", "ours": "ours (MultiTargetTracker)",
             "told": "ours told the association", "ss-told": "Stone Soup EKF+CV told the association"}
    if "told" in trackers and "chosen" in result and not ({"gnn", "jpda"} & set(result["chosen"])):
        log("[told] Stone Soup told the association needs a tuned q: left out")
    kinds = [k for k in ("gnn", "jpda") if k in trackers]
    for f in filters:  # a row of ours (and ours told the association) per filter
        for k in ("ours", "told"):
            if k in trackers:
                kinds.append((k, f))
                if len(filters) > 1:
                    names[(k, f)] = f"{names[k]}, {f}"
                else:
                    names[(k, f)] = names[k]
    if "told" in trackers and ({"gnn", "jpda"} & set(result["chosen"])):
        kinds.append("ss-told")
    rows_of = {names[k]: [] for k in kinds}
    rows_of[RAW] = []
    best_ss = None
    if {"gnn", "jpda"} & set(result["chosen"]):
        # Stone Soup's told reference takes the settings of its tracker that scored best in tuning
        best_ss = min((k for k in ("gnn", "jpda") if k in result["chosen"]),
                      key=lambda k: min((r["gospa"] for r in result["tuning"].get(k) or []), default=math.inf))
    for kind in {"gnn", "jpda"} & set(result["chosen"]) & set(kinds):  # Stone Soup's imports done before any run is timed or capped
        stonesoup_tracker(kind, test[0], **result["chosen"][kind])
    for sc in test:  # every tracker on one scene before the next: same machine state for each
        for kind in kinds:
            if isinstance(kind, tuple):
                run = (run_ours if kind[0] == "ours" else run_ours_told)(sc, kind[1])
            elif kind == "ss-told":
                run = run_stonesoup_told(sc, result["chosen"][best_ss])
            else:
                run = {"est_ids": [], "est_pos": [], "seconds": []}
                capped(lambda k=kind, s=sc, r=run: run_stonesoup(k, s, result["chosen"][k], r), a.time_limit)
            row = evaluate(run, sc)
            rows_of[names[kind]].append(row)
            log(f"[{sc.name}] {names[kind]}: GOSPA {row['gospa']:.1f} m over {row['scans_done']}/{row['scans']} scans, "
                f"{row['ms_per_scan_median']:.1f} ms/scan")
        rows_of[RAW].append(evaluate(raw_plots(sc), sc))
    result["filter"] = a.filter
    if {"ours", "told"} & set(trackers):  # what our tracker ran with (its defaults; each filter a row of its own)
        from immnet.evaluation.scenes import recorded
        from immnet.filters.multi import MultiTargetTracker

        result["ours"] = recorded(MultiTargetTracker())
    result["split"] = a.split
    result["time_limit"] = a.time_limit
    for name, rows in rows_of.items():
        result["test"][name] = mean_rows(rows)
        result["per_scene"][name] = [{k: v for k, v in r.items() if k != "gospa_per_scan"} for r in rows]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.with_suffix(".json").write_text(json.dumps(result, indent=1, default=str) + "\n")
    md = table(result)
    a.out.with_suffix(".md").write_text(md + "\n")
    print(md)
    if a.write_benchmarks:
        spec = test[0].meta["spec"]
        text = (f"Measured {datetime.date.today().isoformat()} on {result['machine']}.\n\n"
                f"`OMP_NUM_THREADS=1 .venv/bin/python benchmarks/mtt_peer.py --scenes {a.scenes}` "
                f"(scenes: `immnet data scenes`; test scenes {', '.join(result['test_scenes'])}; tuned on "
                f"{', '.join(result['train'])}). Radar: {spec['sigma_range']:g} m / {spec['sigma_azimuth_deg']:g} deg / "
                f"{spec['sigma_elevation_deg']:g} deg, scans {spec['dt'] - spec['dt_jitter']:g}-"
                f"{spec['dt'] + spec['dt_jitter']:g} s, Pd {spec['pd']:g}, {spec['clutter']:g} clutter plots per scan, "
                f"cover {spec['max_range'] / 1000:g} km. GOSPA c = 200 m, p = 2, alpha = 2, mean over scans and "
                f"scenes; parts are p-th power sums (m^2). Chosen: "
                + "; ".join(f"{k} q={v['q']:g}, delete after {v['delete_steps']}, confirm at {v['min_points']}"
                            for k, v in result["chosen"].items()) + ".\n\n" + md)
        write_section("Multi-target trackers on scenes", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
