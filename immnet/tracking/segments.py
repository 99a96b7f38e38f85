"""Rows of tracks (a track id and a time per row) -> segments the network tracks on its scan grid.

A radar track that misses more than ``max_coast`` seconds of detections is dropped and restarted at
its next detection, as a tracker on the sensor would (default :data:`MAX_COAST`, ``immnet track
--max-coast``). Per track, in time order:

* a detection starts a new segment if the track has none or its last detection is more than
  ``max_coast`` seconds before it; otherwise it joins the current segment;
* a missed detection (a NaN row) joins the current segment while the last detection is at most
  ``max_coast`` seconds before it (the track coasts); otherwise, and before the track's first
  detection, it has no estimate (NaN).

Within a segment a row's scan is ``k = (t - t_start) / dt``, which must be a whole number (the
network runs on its fixed grid ``net.dt``); the scans between rows are missed detections that no row
asks for. A segment spans at most ``max_coast / dt + 1`` scans per detection, so memory and time are
proportional to the rows, whatever the gaps between them. Segments are tracked as fresh tracks,
batched by span (similar spans together, so that little padding is run), and each row's estimate
is its scan's: the same numbers as tracking each segment alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from decimal import Decimal

import numpy as np

from immnet import keys

MAX_COAST = 30.0
"""Default coasting limit in seconds: a track with no detection for longer is dropped."""


@dataclass
class Segments:
    """``segment [R]`` (-1: the row has no estimate), ``step [R]`` (its scan within the segment),
    ``span [S]`` (scans per segment) and ``z [R, 3]`` (the rows' measurements)."""

    segment: np.ndarray
    step: np.ndarray
    span: np.ndarray
    z: np.ndarray


def check_coast(max_coast: float, dt: float) -> float:
    """``max_coast`` as a float; a ValueError unless it is at least one scan (``inf``: never dropped)."""
    max_coast = float(max_coast)
    if not max_coast >= dt:  # also NaN
        raise ValueError(f"--max-coast must be at least one scan (dt = {dt:g} s), got {max_coast:g}")
    return max_coast


def _join(ids, t, z: np.ndarray, max_coast: float):
    """The coasting rules of the module doc, row by row: ``segment [R]`` (the segment each row joins; -1: no
    estimate), each row's time and its segment's start (Decimals; None for a row without a segment), and the
    number of segments."""
    coast = Decimal(max_coast) if math.isfinite(max_coast) else None
    R = len(ids)
    segment = np.full(R, -1, dtype=np.int64)
    times, starts = [Decimal(v) for v in t], [None] * R
    detected = ~np.isnan(z).any(-1)
    n = 0
    current: dict[str, tuple[int, Decimal, Decimal]] = {}  # track -> (segment, its start, last detection)
    for r in range(R):
        tid, tr = ids[r], times[r]
        seg = current.get(tid)
        alive = seg is not None and (coast is None or tr - seg[2] <= coast)
        if not alive:
            if not detected[r]:
                continue  # no track to coast: no estimate
            seg = (n, tr, tr)
            n += 1
        segment[r], starts[r] = seg[0], seg[1]
        current[tid] = (seg[0], seg[1], tr if detected[r] else seg[2])
    return segment, times, starts, n


def split_rows(ids, t, z: np.ndarray, max_coast: float = MAX_COAST) -> tuple[Segments, np.ndarray]:
    """Segments for a method that takes any interval: each row is one scan at its own time, a segment a
    run of one track's rows whose gaps after a detection are at most ``max_coast`` s (the coasting rules
    of the module doc). Returns the segments and ``offset [R]``: each row's time minus its segment's
    first, in float64 from the exact decimals (epoch times keep their hundredths)."""
    max_coast = float(max_coast)
    if not max_coast > 0:
        raise ValueError(f"--max-coast must be positive, got {max_coast:g}")
    segment, times, starts, n = _join(ids, t, z, max_coast)
    step = np.zeros(len(ids), dtype=np.int64)
    offset = np.full(len(ids), np.nan)
    spans = np.zeros(n, dtype=np.int64)
    for r in np.flatnonzero(segment >= 0):
        step[r], offset[r] = spans[segment[r]], float(times[r] - starts[r])
        spans[segment[r]] += 1
    return Segments(segment, step, spans, z), offset


def split_segments(ids, t, z: np.ndarray, dt: float, max_coast: float, lines, texts) -> Segments:
    """Segments of rows ``ids [R]`` (track), ``t [R]`` (Decimal or float times, increasing per track)
    and ``z [R, 3]`` on a fixed scan grid ``dt`` (a tracker trained at one interval; module doc).
    ``lines``/``texts`` (each row's line and ``t`` as written) name a row in the error for an off-grid time."""
    segment, times, starts, n = _join(ids, t, z, check_coast(max_coast, dt))
    step_dt = Decimal(dt)
    step = np.zeros(len(ids), dtype=np.int64)
    spans = np.zeros(n, dtype=np.int64)
    for r in np.flatnonzero(segment >= 0):
        k_exact = (times[r] - starts[r]) / step_dt
        k = int(k_exact.to_integral_value())
        if abs(k_exact - k) > Decimal("1e-6"):
            raise ValueError(f"line {lines[r]}: time {texts[r]} of track {ids[r]!r} is not a "
                             f"whole number of scans (dt = {dt:g}) after its start {starts[r]}: this tracker was trained "
                             f"at one interval, dt = {dt:g} s; for any scan interval use a method that takes any "
                             f"interval (e.g. --method imm-tuned)")
        step[r], spans[segment[r]] = k, k + 1
    return Segments(segment, step, spans, z)


def batches(span: np.ndarray, batch_size: int = 512) -> list[np.ndarray]:
    """Segment indices in groups of at most ``batch_size``, sorted by span, a group's longest span at
    most twice its shortest (or 16 scans longer): the padding run is at most about the scans run."""
    order = np.argsort(span, kind="stable")
    groups, start = [], 0
    while start < len(order):
        lo = int(span[order[start]])
        end = start + 1
        while end < len(order) and end - start < batch_size and span[order[end]] <= max(2 * lo, lo + 16):
            end += 1
        groups.append(order[start:end])
        start = end
    return groups


def _segment_rows(segs: Segments) -> list[np.ndarray]:
    """Each segment's row indices, in order."""
    order = np.argsort(segs.segment, kind="stable")
    first = np.searchsorted(segs.segment[order], np.arange(len(segs.span) + 1))
    return [order[first[s] : first[s + 1]] for s in range(len(segs.span))]


def _blank(R: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The per-row outputs before anything is tracked: ``state [R, 9]``, ``mode_probs [R, 4]``, ``state_cov [R, 9,
    9]``, NaN."""
    return np.full((R, 9), np.nan), np.full((R, 4), np.nan), np.full((R, 9, 9), np.nan)


def _scan_times(times: np.ndarray, max_interval: float | None) -> tuple[np.ndarray, np.ndarray]:
    """A segment's scan times and where its rows are among them: the rows' own times, and where two rows are more
    than ``max_interval`` apart (a network trained over intervals up to it), the gap cut into equal intervals by
    missed scans (a gap is a gap: the tracker coasts through it, at intervals it knows)."""
    if max_interval is None or len(times) < 2:
        return times, np.arange(len(times))
    gaps = np.diff(times)
    cuts = np.maximum(1, np.ceil(gaps / (max_interval + 1e-6 * max(1.0, max_interval)))).astype(np.int64)  # check_dt's
    # tolerance: a gap a hair over the range's end is one scan the network takes, not two halves it may not
    pos = np.concatenate([[0], np.cumsum(cuts)])
    full = np.empty(pos[-1] + 1)
    for i, (g, k) in enumerate(zip(gaps, cuts)):
        full[pos[i] : pos[i + 1]] = times[i] + g * np.arange(k) / k
    full[-1] = times[-1]
    return full, pos


def track_rows(method, segs: Segments, offset: np.ndarray, batch_size: int = 512, return_cov: bool = False,
               max_interval: float | None = None, r: float | None = None, meas_cov: np.ndarray | None = None,
               one_row_interval: float = 1.0):
    """``state [R, 9]``, ``mode_probs [R, 4]`` per row of :func:`split_rows`' segments, each tracked as a
    fresh track by ``method.track(batch)`` with ``t [B, T]`` (its rows' times since its first); padding
    after a segment's end is missed detections, its times continuing at the segment's median spacing
    (strictly increasing). ``max_interval``: a gap between rows longer than it is cut into equal intervals by
    missed scans (:func:`_scan_times`; a network trained over a range of intervals). ``mode_probs`` NaN where the
    method has none. With ``return_cov`` a third, ``state_cov [R, 9, 9]`` from the method's output, NaN where it
    gives none. ``r``: every track's measurement std (m), the batch's ``r`` for a method told it (the real-flight
    filters' ``r: data``). ``meas_cov [R, 3, 3]``: each row's measurement covariance (m^2, NaN where missed), the
    batch's ``meas_cov [B, T, 3, 3]`` (NaN at the scans no row fills). ``one_row_interval``: the spacing of the padding
    after a segment of one row, which has none of its own (s; a network trained over a range of intervals needs one
    inside it)."""
    from tensordict import TensorDict

    import torch

    told = None if r is None else float(r)  # ``r`` names rows below
    state, probs, cov = _blank(len(segs.segment))
    segment_rows = _segment_rows(segs)
    scans = [_scan_times(offset[r], max_interval) for r in segment_rows]  # its scan times, its rows' scans among them
    span = np.array([len(full) for full, _ in scans], dtype=np.int64)  # the rows and the missed scans cut in
    for g in batches(span, batch_size):
        T, rows = int(span[g].max()), [segment_rows[s] for s in g]
        z = np.full((len(rows), T, 3), np.nan)
        t = np.zeros((len(rows), T))
        dt = np.ones(len(rows))
        for i, r in enumerate(rows):
            full, pos = scans[g[i]]
            z[i, pos] = segs.z[r]
            t[i, : len(full)] = full
            gaps = np.diff(full)
            dt[i] = float(np.median(gaps)) if len(gaps) else float(one_row_interval)
            t[i, len(full):] = full[-1] + dt[i] * np.arange(1, T - len(full) + 1)
        batch = TensorDict({keys.MEASUREMENTS: torch.from_numpy(z), keys.TIME: torch.from_numpy(t),
                            keys.DT: torch.from_numpy(dt)}, batch_size=[len(rows)])
        if told is not None:
            batch.set(keys.R, torch.full((len(rows),), told, dtype=torch.float64))
        if meas_cov is not None:
            c = np.full((len(rows), T, 3, 3), np.nan)
            for i, r in enumerate(rows):
                c[i, scans[g[i]][1]] = meas_cov[r]
            batch.set(keys.MEAS_COV, torch.from_numpy(c))
        if hasattr(method, "check"):
            method.check(batch)
        out = method.track(batch)
        _scatter(out, return_cov, rows, [scans[s][1] for s in g], state, probs, cov)
    return (state, probs, cov) if return_cov else (state, probs)


def _scatter(out, return_cov: bool, rows, scans, state, probs, cov) -> None:
    """Each segment's rows' estimates from a batch's output ``out`` (segment ``i``'s rows ``rows[i]`` at its scans
    ``scans[i]``) into the per-row ``state``, ``mode_probs`` and, with ``return_cov``, ``state_cov`` (float64; those
    the output lacks stay NaN)."""
    st = out[keys.STATE].double().numpy()
    pr = out[keys.MODE_PROBS].double().numpy() if keys.MODE_PROBS in out.keys() else None
    cv = out[keys.STATE_COV].double().numpy() if return_cov and keys.STATE_COV in out.keys() else None
    for i, (r, pos) in enumerate(zip(rows, scans)):
        state[r] = st[i, pos]
        if pr is not None:
            probs[r] = pr[i, pos]
        if cv is not None:
            cov[r] = cv[i, pos]


def track_segments(tracker, segs: Segments, batch_size: int = 512, return_cov: bool = False):
    """``state [R, 9]``, ``mode_probs [R, 4]`` (float64) per row: each row's estimate at its scan of its
    segment, each segment tracked as a fresh track by ``tracker.track``; NaN where a row has none. With
    ``return_cov`` a third, ``state_cov [R, 9, 9]`` (``Tracker.track``'s, which refuses experts without one)."""
    state, probs, cov = _blank(len(segs.segment))
    segment_rows = _segment_rows(segs)
    for g in batches(segs.span, batch_size):
        T, rows = int(segs.span[g].max()), [segment_rows[s] for s in g]
        z = np.full((len(rows), T, 3), np.nan)  # float64: the tracker moves each track into its frame first
        for i, r in enumerate(rows):
            z[i, segs.step[r]] = segs.z[r]
        out = tracker.track(z, batch_size=len(rows), return_cov=return_cov)
        _scatter(out, return_cov, rows, [segs.step[r] for r in rows], state, probs, cov)
    return (state, probs, cov) if return_cov else (state, probs)
