"""Many-target metrics: GOSPA per scan and its parts, and the track-identity metrics over a scene.

GOSPA (Rahmathullah, Garcia-Fernandez & Svensson 2017) between a truth set ``X`` (``n`` points) and an estimate
set ``Y`` (``m`` points), cut-off ``c``, order ``p``, ``alpha`` (2: the split into missed and false targets)::

    GOSPA = ( min_gamma sum_{(i, j) in gamma} d(x_i, y_j)^p  +  c^p / alpha (n + m - 2 |gamma|) )^(1/p)

over the partial assignments ``gamma`` whose pairs are closer than ``c``. It is computed as Stone Soup's
``GOSPAMetric`` computes it: the optimal assignment of ``min(d, c)^p`` (scipy's ``linear_sum_assignment``; the
``min(n, m)`` pairs it assigns), then every pair at ``d >= c`` counted as one missed and one false target. The
parts are Stone Soup's, p-th-power sums (not their p-th roots)::

    localisation = sum_{assigned, d < c} d^p        missed = c^p / alpha * (truths not assigned below c)
    false = c^p / alpha * (estimates not assigned below c)        gospa = (localisation + missed + false)^(1/p)

(Stone Soup splits the parts only for ``alpha = 2``; here the same formula holds for any ``alpha``.)
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment


def _points(name: str, a) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.size == 0:
        return a.reshape(0, a.shape[-1] if a.ndim == 2 else 3)
    if a.ndim != 2:
        raise ValueError(f"{name} must be an array of points [n, d], got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} has a non-finite coordinate")
    return a


def gospa(truth: np.ndarray, estimates: np.ndarray, c: float = 200.0, p: float = 2.0, alpha: float = 2.0) -> dict:
    """GOSPA of one scan (module doc): ``truth [n, d]``, ``estimates [m, d]`` (positions, m).

    Returns ``gospa`` (the distance), ``localisation``, ``missed``, ``false`` (p-th power sums, Stone Soup's parts),
    ``assignment`` (``[n]`` int: the estimate assigned to each truth below the cut-off, -1 for none) and the counts
    ``n_missed``, ``n_false``."""
    if not (np.isfinite(c) and c > 0):
        raise ValueError(f"gospa: c must be finite and > 0, got {c}")
    if not (np.isfinite(p) and p >= 1):
        raise ValueError(f"gospa: p must be finite and >= 1, got {p}")
    if not (0 < alpha <= 2):
        raise ValueError(f"gospa: alpha must be in (0, 2], got {alpha}")
    X, Y = _points("truth", truth), _points("estimates", estimates)
    n, m = len(X), len(Y)
    if n and m and X.shape[1] != Y.shape[1]:
        raise ValueError(f"gospa: truth has {X.shape[1]} coordinates, estimates {Y.shape[1]}")
    assignment = np.full(n, -1, dtype=np.int64)
    loc = 0.0
    if n and m:
        d = np.sqrt(((X[:, None, :] - Y[None, :, :]) ** 2).sum(-1))
        cost = np.minimum(d, c) ** p
        rows, cols = linear_sum_assignment(cost)
        close = d[rows, cols] < c
        assignment[rows[close]] = cols[close]
        loc = float((d[rows[close], cols[close]] ** p).sum())
    n_assigned = int((assignment >= 0).sum())
    dummy = c**p / alpha
    n_missed, n_false = n - n_assigned, m - n_assigned
    missed, false = dummy * n_missed, dummy * n_false
    return {"gospa": (loc + missed + false) ** (1.0 / p), "localisation": loc, "missed": missed, "false": false,
            "assignment": assignment, "n_missed": n_missed, "n_false": n_false}


def track_metrics(truth_ids: Sequence, truth_pos: Sequence, est_ids: Sequence, est_pos: Sequence,
                  c: float = 200.0, p: float = 2.0, alpha: float = 2.0) -> dict:
    """GOSPA per scan and the identity metrics of a scene: per scan ``s`` the truths' ids ``truth_ids[s] [n_s]``
    and positions ``truth_pos[s] [n_s, 3]``, the estimates' (track) ids ``est_ids[s] [m_s]`` and positions
    ``est_pos[s] [m_s, 3]``.

    Each scan's GOSPA assignment (``gospa``: pairs closer than ``c``) says which estimate a truth has there. For a
    truth, its *present* scans are those it appears in, and it is *assigned* at a present scan where GOSPA pairs it:

    - ``id_switches``: assigned scans whose estimate id differs from the id at the truth's previous assigned scan
      (the nearest earlier one, unassigned scans between them skipped), summed over truths;
    - ``fragmentations``: assigned scans that follow an unassigned present scan of the same truth and come after an
      earlier assigned scan of it (its tracking interrupted, then resumed), summed over truths;
    - ``continuity``: the mean over truths of the longest run of consecutive present scans assigned to one estimate
      id, divided by the truth's present scans (SIAP's longest track segment; 1: one track followed it throughout);
    - ``coverage``: assigned truth-scans over present truth-scans (all truths together).

    Returns those and ``gospa``, ``localisation``, ``missed``, ``false`` (means over scans), ``per_scan`` (a list of
    ``gospa`` dicts) and ``per_truth`` (``{truth id: {"present", "assigned", "switches", "fragmentations",
    "longest"}}``)."""
    lists = (truth_ids, truth_pos, est_ids, est_pos)
    if len({len(v) for v in lists}) != 1:
        raise ValueError(f"track_metrics: truth_ids, truth_pos, est_ids and est_pos need one entry per scan, got "
                         f"{', '.join(str(len(v)) for v in lists)}")
    per_scan, per_truth, seen = [], {}, {}  # seen: each truth's last assigned id, a gap since it, its current run
    for s, (tid, tpos, eid, epos) in enumerate(zip(*lists)):
        tid, eid = np.asarray(tid).reshape(-1), np.asarray(eid).reshape(-1)
        g = gospa(tpos, epos, c, p, alpha)
        if len(tid) != len(g["assignment"]) or len(eid) != len(_points("estimates", epos)):
            raise ValueError(f"track_metrics: scan {s} has ids and positions of different counts")
        per_scan.append(g)
        for k, truth in enumerate(tid.tolist()):
            j = g["assignment"][k]
            rec = per_truth.setdefault(truth, dict.fromkeys(("present", "assigned", "switches", "fragmentations",
                                                             "longest"), 0))
            mem = seen.setdefault(truth, {"last_id": None, "gap": False, "run": 0, "run_id": None})
            rec["present"] += 1
            if j < 0:
                mem["gap"] = mem["last_id"] is not None  # a gap once assigned (gap is False until then)
                mem["run"], mem["run_id"] = 0, None
                continue
            est = eid[j].item()
            rec["assigned"] += 1
            if mem["last_id"] is not None:
                rec["switches"] += int(est != mem["last_id"])
                rec["fragmentations"] += int(mem["gap"])
            mem["last_id"], mem["gap"] = est, False
            mem["run"] = mem["run"] + 1 if mem["run_id"] == est else 1
            mem["run_id"] = est
            rec["longest"] = max(rec["longest"], mem["run"])
    present = sum(r["present"] for r in per_truth.values())
    return {
        **{k: float(np.mean([g[k] for g in per_scan])) if per_scan else 0.0
           for k in ("gospa", "localisation", "missed", "false")},
        "id_switches": sum(r["switches"] for r in per_truth.values()),
        "fragmentations": sum(r["fragmentations"] for r in per_truth.values()),
        "continuity": float(np.mean([r["longest"] / r["present"] for r in per_truth.values()])) if per_truth else 1.0,
        "coverage": sum(r["assigned"] for r in per_truth.values()) / present if present else 1.0,
        "per_scan": per_scan, "per_truth": per_truth,
    }
