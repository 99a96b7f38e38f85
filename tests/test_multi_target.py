"""Many targets: GOSPA and the identity metrics (against Stone Soup and hand counts), the multi-target tracker's
filter (against the single-target IMMs), association on hand-made scenes, clutter, and a Monte Carlo check against
the IMM told the association (docs/tracking.md, "Many targets")."""

from __future__ import annotations

import datetime

import numpy as np
import pytest

from immnet.evaluation.gospa import gospa, track_metrics


# --- GOSPA ---------------------------------------------------------------------------------------------------------

def test_gospa_matches_stone_soup_on_random_sets():
    """Stone Soup 1.9.1's ``GOSPAMetric.compute_gospa_metric``: the distance, its three parts (p-th power sums) and the
    truth-to-estimate assignment, on random sets of 0 to 6 points each (empty truth, empty estimates), to 1e-9."""
    from stonesoup.metricgenerator.ospametric import GOSPAMetric
    from stonesoup.types.state import State

    rng = np.random.default_rng(0)
    stamp = datetime.datetime(2024, 1, 1)
    checked = {"empty truth": 0, "empty estimates": 0, "both": 0}
    for c, p in ((200.0, 2.0), (150.0, 1.0), (300.0, 3.0)):
        metric = GOSPAMetric(c=c, p=p)
        for _ in range(120):
            n, m = (int(v) for v in rng.integers(0, 7, 2))
            if n == 0 and m == 0:
                continue  # Stone Soup needs a timestamp from some state (the empty case is checked below)
            X, Y = rng.uniform(0, 500, (n, 3)), rng.uniform(0, 500, (m, 3))
            ref, ref_assign = metric.compute_gospa_metric([State(y.reshape(3, 1), timestamp=stamp) for y in Y],
                                                          [State(x.reshape(3, 1), timestamp=stamp) for x in X])
            ours = gospa(X, Y, c=c, p=p)
            scale = max(1.0, ref.value["distance"] ** p)
            for key in ("localisation", "missed", "false"):
                assert abs(ours[key] - ref.value[key]) <= 1e-9 * scale, (key, n, m)
            assert abs(ours["gospa"] - ref.value["distance"]) <= 1e-9 * max(1.0, ref.value["distance"])
            if n and m:
                assert (ours["assignment"] == np.asarray(ref_assign)).all()
                checked["both"] += 1
            else:
                checked["empty truth" if n == 0 else "empty estimates"] += 1
    assert min(checked.values()) > 5, checked
    empty = gospa(np.zeros((0, 3)), np.zeros((0, 3)))
    assert empty["gospa"] == 0.0 and len(empty["assignment"]) == 0


def test_gospa_by_hand():
    """Two truths, three estimates: one pair at 30 m, one at 250 m (beyond c = 200: a missed and a false target)."""
    X = np.array([[0.0, 0, 0], [1000, 0, 0]])
    Y = np.array([[30.0, 0, 0], [1250, 0, 0], [5000, 0, 0]])
    g = gospa(X, Y, c=200.0, p=2.0)
    assert g["localisation"] == pytest.approx(900.0)
    assert g["missed"] == pytest.approx(200.0**2 / 2)
    assert g["false"] == pytest.approx(2 * 200.0**2 / 2)
    assert g["gospa"] == pytest.approx((900.0 + 3 * 20000.0) ** 0.5)
    assert g["assignment"].tolist() == [0, -1]


def test_track_metrics_counts_switches_fragments_continuity():
    """One truth over 8 scans, estimates by hand: ids 7 7 _ 7 9 9 _ 9 (``_``: no estimate near it): one switch
    (7 -> 9), two fragmentations (the resumptions at scans 3 and 7), longest run 2 of 8 present scans."""
    ids = [7, 7, None, 7, 9, 9, None, 9]
    truth_ids, truth_pos, est_ids, est_pos = [], [], [], []
    for s, e in enumerate(ids):
        x = np.array([[100.0 * s, 0.0, 0.0]])
        truth_ids.append(np.array([1]))
        truth_pos.append(x)
        if e is None:
            est_ids.append(np.array([3]))
            est_pos.append(x + 5000.0)  # a false track far away
        else:
            est_ids.append(np.array([e]))
            est_pos.append(x + 10.0)
    out = track_metrics(truth_ids, truth_pos, est_ids, est_pos, c=200.0)
    assert out["id_switches"] == 1
    assert out["fragmentations"] == 2
    assert out["continuity"] == pytest.approx(2 / 8)
    assert out["coverage"] == pytest.approx(6 / 8)
    expected = [gospa(t, e)["gospa"] for t, e in zip(truth_pos, est_pos)]
    assert out["gospa"] == pytest.approx(np.mean(expected))
    with pytest.raises(ValueError, match="one entry per scan"):
        track_metrics(truth_ids, truth_pos[:-1], est_ids, est_pos)
