"""The multi-target peer: Stone Soup's GNN and JPDA trackers on the scenes of ``immnet data scenes``, tuned on the
training scenes only, against ours (``immnet.tracking.multi.MultiTargetTracker``, where importable) in the same run.

Run (Stone Soup is the ``bench`` extra: ``pip install -e '.[bench]'``)::

    immnet data scenes --samples collections/quickstart collections/switzerland --out data/scenes --n 3
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/mtt_peer.py --scenes data/scenes [--tune-scenes 2] \\
        [--trackers gnn,jpda,ours] [--out results/mtt_peer] [--write-benchmarks]

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

Tuning (training scenes only, the first ``--tune-scenes`` of split ``train``): the grid ``GRID`` over ``q``,
``delete_steps`` and ``min_points``; the choice is the lowest mean GOSPA over the scans of those scenes. The chosen
settings then run on every ``test`` scene. Ours runs with its defaults, told the scenes' detection probability and
clutter density (nothing of it tuned on the test scenes).

Scoring, per scan: GOSPA (c = 200 m, p = 2, alpha = 2) between the positions of the aircraft in cover and the
positions of the tracks a tracker reports at that scan (Stone Soup: its tracks, confirmed by construction; ours:
the confirmed ``TrackReport``s), with its parts (Stone Soup's p-th power sums) and the identity metrics where
``immnet.evaluation.gospa.track_metrics`` is importable (else Stone Soup's ``GOSPAMetric``: GOSPA and parts only).
Time: the wall time of each scan's update (detections built outside it), its median and mean over the scans.

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

C, P, ALPHA = 200.0, 2.0, 2.0
GRID = {"q": (0.5, 5.0, 50.0), "delete_steps": (3, 5), "min_points": (3, 4)}
"""The tuning grid of both Stone Soup trackers."""
FIXED = {"missed_distance": 4.0, "init_speed": 300.0, "tentative_steps": 2, "prob_gate": 0.9999}
EPOCH = datetime.datetime(1970, 1, 1)
RAW = "raw plots of the aircraft (no tracker)"


# --- scoring: the one place that computes GOSPA ---------------------------------------------------------------------
def score(truth_ids: list, truth_pos: list, est_ids: list, est_pos: list) -> dict:
    """GOSPA per scan (means over the scans) and, where ``immnet.evaluation.gospa`` is importable, the identity metrics;
    else Stone Soup's ``GOSPAMetric`` for GOSPA and its parts."""
    try:
        from immnet.evaluation.gospa import track_metrics
    except ImportError:
        track_metrics = None
    if track_metrics is not None:
        m = track_metrics(truth_ids, truth_pos, est_ids, est_pos, c=C, p=P, alpha=ALPHA)
        per = m.pop("per_scan")
        m.pop("per_truth", None)
        return {**m, "gospa_per_scan": [float(g["gospa"]) for g in per], "scored_by": "immnet.evaluation.gospa"}
    from stonesoup.metricgenerator.ospametric import GOSPAMetric
    from stonesoup.types.state import State

    metric = GOSPAMetric(c=C, p=P)
    rows = []
    for tp, ep in zip(truth_pos, est_pos):
        truths = [State(np.asarray(x, float).reshape(3, 1), timestamp=EPOCH) for x in tp]
        ests = [State(np.asarray(x, float).reshape(3, 1), timestamp=EPOCH) for x in ep]
        if not truths and not ests:
            rows.append(dict.fromkeys(("distance", "localisation", "missed", "false"), 0.0))
            continue
        single, _ = metric.compute_gospa_metric(ests, truths)
        rows.append(single.value)
    mean = {k: float(np.mean([r[k] for r in rows])) for k in ("distance", "localisation", "missed", "false")}
    return {"gospa": mean["distance"], "localisation": mean["localisation"], "missed": mean["missed"],
            "false": mean["false"], "gospa_per_scan": [float(r["distance"]) for r in rows],
            "scored_by": "stonesoup GOSPAMetric"}


# --- Stone Soup -----------------------------------------------------------------------------------------------------
def clutter_density(scene: Scene) -> float:
    """The scene's clutter plots per unit of elevation (rad) x bearing (rad) x range (m): Poisson mean over the cover."""
    s = scene.meta["spec"]
    vol = math.radians(s["max_elevation"] - s["min_elevation"]) * 2 * math.pi * (s["max_range"] - s["min_range"])
    return s["clutter"] / vol


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
                                          deleter=UpdateTimeStepsDeleter(tentative_steps),
                                          data_associator=GNNWith2DAssignment(gnn_hyp), updater=updater,
                                          min_points=min_points)
    deleter = UpdateTimeStepsDeleter(delete_steps)
    if kind == "gnn":
        return MultiTargetTracker(initiator=initiator, deleter=deleter, detector=None,
                                  data_associator=GNNWith2DAssignment(gnn_hyp), updater=updater), mm
    pda = PDAHypothesiser(predictor, updater, clutter_spatial_density=clutter_density(scene), prob_detect=s["pd"],
                          prob_gate=prob_gate)
    return MultiTargetMixtureTracker(initiator=initiator, deleter=deleter, detector=None,
                                     data_associator=JPDA(pda), updater=updater), mm


def run_stonesoup(kind: str, scene: Scene, params: dict) -> dict:
    """One scene through a Stone Soup tracker: per scan its tracks' positions and ids, and the seconds of each update."""
    from stonesoup.types.angle import Bearing, Elevation
    from stonesoup.types.array import StateVector
    from stonesoup.types.detection import Detection

    tracker, mm = stonesoup_tracker(kind, scene, **params)
    est_ids, est_pos, seconds, number = [], [], [], {}  # Stone Soup's track ids (text) numbered in order of birth
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
        seconds.append(time.perf_counter() - t0)
        tracks = sorted(tracks, key=lambda tr: tr.id)
        est_ids.append(np.array([number.setdefault(tr.id, len(number)) for tr in tracks], dtype=np.int64))
        est_pos.append(np.array([np.asarray(tr.state_vector, float).ravel()[[0, 2, 4]] for tr in tracks]).reshape(-1, 3))
    return {"est_ids": est_ids, "est_pos": est_pos, "seconds": seconds}


# --- ours -----------------------------------------------------------------------------------------------------------
def ours_available() -> bool:
    try:
        from immnet.tracking.multi import MultiTargetTracker  # noqa: F401
    except ImportError:
        return False
    return True


def run_ours(scene: Scene, associator: str = "gnn") -> dict:
    from immnet.tracking.multi import MultiTargetTracker

    s = scene.meta["spec"]
    # our tracker works in ENU: the clutter density per m^3 at the cover's mean volume element
    vol = (2 * math.pi / 3) * (s["max_range"] ** 3 - s["min_range"] ** 3) * (
        math.sin(math.radians(s["max_elevation"])) - math.sin(math.radians(s["min_elevation"])))
    tracker = MultiTargetTracker(associator=associator, pd=s["pd"], clutter_density=s["clutter"] / vol)
    est_ids, est_pos, seconds = [], [], []
    for t, plots, cov in scene.scans():
        t0 = time.perf_counter()
        reports = tracker.step(t, plots, cov)
        seconds.append(time.perf_counter() - t0)
        conf = [r for r in reports if r.confirmed]
        est_ids.append(np.array([r.track_id for r in conf], dtype=np.int64))
        est_pos.append(np.array([np.asarray(r.state, float)[[0, 3, 6]] for r in conf]).reshape(-1, 3))
    return {"est_ids": est_ids, "est_pos": est_pos, "seconds": seconds}


# --- the run --------------------------------------------------------------------------------------------------------
def evaluate(run: dict, scene: Scene) -> dict:
    tid = [scene.truth(k)[1] for k in range(len(scene))]
    tpos = [scene.truth(k)[0] for k in range(len(scene))]
    m = score(tid, tpos, run["est_ids"], run["est_pos"])
    sec = np.asarray(run["seconds"])
    return {**m, "ms_per_scan_median": float(np.median(sec) * 1e3), "ms_per_scan_mean": float(sec.mean() * 1e3),
            "scans": len(scene)}


def truth_told(scene: Scene) -> dict:
    """No tracker: each scan's detections of the aircraft (the plots that are not clutter) as the estimates: what the
    radar's plots are worth without association or filtering."""
    ids, pos = [], []
    for k in range(len(scene)):
        a, b = scene.plot_offsets[k], scene.plot_offsets[k + 1]
        src = scene.plot_source[a:b]
        ids.append(src[src >= 0])
        pos.append(scene.plots[a:b][src >= 0])
    return {"est_ids": ids, "est_pos": pos, "seconds": [0.0] * len(scene)}


def mean_rows(rows: list[dict]) -> dict:
    keys = ("gospa", "localisation", "missed", "false", "ms_per_scan_median", "ms_per_scan_mean")
    out = {}
    for k in keys:
        out[k] = float(np.mean([r[k] for r in rows]))
    # GOSPA over all scans together (scenes weighted by their scans)
    out["gospa_all_scans"] = float(np.mean(np.concatenate([r["gospa_per_scan"] for r in rows])))
    for k in ("id_switches", "fragmentations"):
        if all(k in r for r in rows):
            out[k] = int(sum(r[k] for r in rows))
    if all("continuity" in r for r in rows):
        out["continuity"] = float(np.mean([r["continuity"] for r in rows]))
    return out


def tune(kind: str, scenes: list[Scene], log) -> tuple[dict, list]:
    grid = []
    for q, ds, mp in itertools.product(GRID["q"], GRID["delete_steps"], GRID["min_points"]):
        params = {**FIXED, "q": q, "delete_steps": ds, "min_points": mp}
        rows = [evaluate(run_stonesoup(kind, sc, params), sc) for sc in scenes]
        g = float(np.mean(np.concatenate([r["gospa_per_scan"] for r in rows])))
        grid.append({"q": q, "delete_steps": ds, "min_points": mp, "gospa": g,
                     "ms_per_scan_median": float(np.mean([r["ms_per_scan_median"] for r in rows]))})
        log(f"[tune {kind}] q={q:g} delete_steps={ds} min_points={mp}: GOSPA {g:.1f} m")
    best = min(grid, key=lambda r: r["gospa"])
    return {**FIXED, "q": best["q"], "delete_steps": best["delete_steps"], "min_points": best["min_points"]}, grid


def table(result: dict) -> str:
    lines = ["| tracker | mean GOSPA (m) | localisation | missed | false | id switches | fragmentations | "
             "ms per scan (median) | ms per scan (mean) |", "|---|---|---|---|---|---|---|---|---|"]
    for name, m in result["test"].items():
        lines.append(f"| {name} | {m['gospa']:.1f} | {m['localisation']:.0f} | {m['missed']:.0f} | {m['false']:.0f} | "
                     f"{m.get('id_switches', 'n/a')} | {m.get('fragmentations', 'n/a')} | "
                     f"{m['ms_per_scan_median']:.1f} | {m['ms_per_scan_mean']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", required=True, type=Path, help="a scene set of `immnet data scenes`")
    ap.add_argument("--tune-scenes", type=int, default=2, help="training scenes to tune on (default 2)")
    ap.add_argument("--test-scenes", type=int, default=3, help="test scenes to evaluate on (default 3)")
    ap.add_argument("--trackers", default="gnn,jpda,ours", help="of gnn, jpda, ours (default all)")
    ap.add_argument("--params", type=Path, default=None,
                    help="a previous OUT.json: take its tuned settings instead of tuning again")
    ap.add_argument("--out", type=Path, default=Path("results/mtt_peer"), help="OUT.json and OUT.md")
    ap.add_argument("--write-benchmarks", action="store_true", help="rewrite the section of BENCHMARKS.md")
    ap.add_argument("--quiet", action="store_true")
    a = ap.parse_args(argv)
    trackers = [t.strip() for t in a.trackers.split(",") if t.strip()]
    unknown = set(trackers) - {"gnn", "jpda", "ours"}
    if unknown:
        ap.error(f"--trackers: unknown {', '.join(sorted(unknown))} (gnn, jpda, ours)")

    def log(msg):
        if not a.quiet:
            print(msg, file=sys.stderr, flush=True)

    index = load_index(a.scenes)
    entries = {s: [e for e in index["scenes"] if e["split"] == s] for s in ("train", "test")}
    train = [load_scene(a.scenes / e["file"]) for e in entries["train"][: a.tune_scenes]]
    test = [load_scene(a.scenes / e["file"]) for e in entries["test"][: a.test_scenes]]
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
        if previous is not None and kind in previous.get("chosen", {}):
            result["chosen"][kind] = previous["chosen"][kind]
            result["tuning"][kind] = previous.get("tuning", {}).get(kind, [])
        else:
            result["chosen"][kind], result["tuning"][kind] = tune(kind, train, log)
        log(f"[{kind}] chosen {result['chosen'][kind]}")
    names = {"gnn": "Stone Soup GNN (EKF, CV)", "jpda": "Stone Soup JPDA (EKF, CV)", "ours": "ours (MultiTargetTracker)"}
    if "ours" in trackers and not ours_available():
        log("[ours] immnet.tracking.multi is not importable here: left out")
        trackers.remove("ours")
    rows_of = {names[k]: [] for k in trackers}
    rows_of[RAW] = []
    for sc in test:  # every tracker on one scene before the next: same machine state for each
        for kind in trackers:
            run = run_ours(sc) if kind == "ours" else run_stonesoup(kind, sc, result["chosen"][kind])
            row = evaluate(run, sc)
            rows_of[names[kind]].append(row)
            log(f"[{sc.name}] {kind}: GOSPA {row['gospa']:.1f} m, {row['ms_per_scan_median']:.1f} ms/scan")
        rows_of[RAW].append(evaluate(truth_told(sc), sc))
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
