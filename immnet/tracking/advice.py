"""What shipped weights' provenance says about a user's data: a note where, at the data's scan interval, the weights
were measured behind a model-based filter (docs/tracking.md, "Which tracker for which scans").

``scripts/make_shipped.py`` scores the general weights by scan interval beside ``imm-ekf-general``, IMMNet with nothing
learned tuned on the same training data, on 3D-LAST over U[0.5, 12] s, and writes the pooled RMSE of each interval
bin into the provenance (``interval_bins``: ``data``, ``edges``, ``network``, ``filter``, ``rmse`` per method and
bin). ``immnet track`` reads it for the weights it loads and, where the network's RMSE in the bin of the data's
median scan interval is above the filter's, says so on stderr, naming the filter to try. The tracking itself is
unchanged: the note is advice from measurements, not a switch.

With the general weights (``--weights general``), ``immnet track`` also says where another shipped network was
trained for the data's median scan interval and a provenance measured it ahead of the general one (``weights_note``:
``real-5s`` at 4.5-5.5 s, ``real-11s`` at 10-12 s, ``real`` at 1 s, each on real flights), naming ``--weights`` to
try. With the bank (the default), which runs those networks itself, the general network's interval note is said, with
what another member's provenance measured where one was trained for those scans (``bank_note``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from immnet.checkpoints import GENERAL, SHIPPED, WEIGHTS, provenance_file, shipped


def load_provenance(ckpt) -> dict | None:
    """The provenance JSON beside shipped weights (``immnet.checkpoints.provenance_file``), or None where there is
    none (a checkpoint of one's own) or it cannot be read as JSON."""
    path = provenance_file(Path(ckpt))
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def track_intervals(ids, t) -> np.ndarray:
    """The scan intervals of CSV rows: the differences of each track's times (rows of a track in time order, as
    ``immnet.data.csvio.read_tracks_csv`` checks them), all tracks together, in seconds."""
    t = np.asarray([float(v) for v in t], dtype=np.float64)
    ids = np.asarray(ids)
    order = np.argsort(ids, kind="stable")  # each track's rows together, in their time order
    return np.diff(t[order])[ids[order][1:] == ids[order][:-1]]


def _median(intervals) -> float | None:
    """The median of the finite ``intervals`` (s), None where there is none."""
    dt = np.asarray(intervals, dtype=np.float64)
    dt = dt[np.isfinite(dt)]
    return float(np.median(dt)) if dt.size else None


def _span(provenance: dict, median: float) -> tuple[float, float] | None:
    """The scan intervals a shipped network was trained for (its provenance's ``interval_range``, or its one
    ``scan_interval``) where ``median`` lies in them (to 1e-6); None otherwise."""
    span = provenance.get("interval_range") or [provenance.get("scan_interval")] * 2
    if span[0] is None or not float(span[0]) * (1 - 1e-6) <= median <= float(span[1]) * (1 + 1e-6):
        return None
    return float(span[0]), float(span[1])


def _takes(provenance: dict, median: float) -> bool:
    """Whether a shipped network runs on a track scanned every ``median`` s: ``immnet.tracking.bank.accepts`` of a
    network with the intervals its provenance names (a network trained over a range takes an interval longer than the
    range cut into equal ones by missed scans: ``real-5s`` takes 10 s scans as two of 5 s; one trained at one interval,
    that interval; a provenance that names none, the 3D-LAST network's, counts as none)."""
    span, dt = provenance.get("interval_range"), provenance.get("scan_interval")
    return (span is not None or dt is not None) and bool(_accepts(span, dt, [median]).all())


def _accepts(span, dt, intervals) -> np.ndarray:
    """Whether a network trained over the intervals ``span`` (or at the one interval ``dt``) takes each finite one of
    ``intervals`` (s) between two scans of a track (a non-finite one: True): ``immnet.tracking.bank.accepts`` (an
    interval longer than the span cut into equal ones by missed scans, each then inside it, ``trained_for``'s
    tolerance), per interval."""
    import torch

    from immnet.tracking.bank import accepts

    iv = np.asarray(intervals, dtype=np.float64).reshape(-1)
    iv = np.where(np.isfinite(iv), iv, np.nan)
    rows = torch.from_numpy(np.stack([np.full(iv.shape, np.nan), iv], -1))  # each a track; scan 0's interval: none
    return accepts(SimpleNamespace(interval_range=span, dt=dt), rows).numpy()


def _table_scans(name: str) -> dict:
    """The intervals of the shipped network ``name`` as a provenance names them, from the weights table's ``scans``
    (``immnet/pretrained/weights.json``: ``[lo, hi]``, one interval where they are equal), for :func:`_takes`."""
    lo, hi = (float(v) for v in WEIGHTS[name]["scans"])
    return {"interval_range": [lo, hi]} if lo < hi else {"scan_interval": lo}


def _ahead(tests, name: str, ref: str) -> tuple[str, float, float] | None:
    """``(set name, name's RMSE, ref's RMSE)`` of the first of ``tests`` (a provenance's ``tests`` items, ``(set name,
    entry)``) where the registry method ``name`` scored below ``ref`` in the same run; None where none did."""
    for set_name, test in tests:
        rmse = {m: (v or {}).get("avg") for m, v in test.get("metrics", {}).items()}
        a, b = rmse.get(name), rmse.get(ref)
        if a is not None and b is not None and a < b:
            return set_name, a, b
    return None


def interval_note(provenance: dict | None, intervals, whose: str = "these weights were") -> str | None:
    """A note (one line) where the provenance's ``interval_bins`` put the network (``whose``, with its verb) behind its
    filter in the bin of the median of ``intervals`` (seconds; non-finite values ignored); None where it does not,
    where the median lies outside the bins, or where the provenance has no bins."""
    from immnet.evaluation.metrics import interval_bin

    bins, median = (provenance or {}).get("interval_bins"), _median(intervals)
    if not bins or median is None:
        return None
    edges = [float(e) for e in bins["edges"]]
    i = int(interval_bin(median, edges))
    if i < 0:
        return None
    net, ref = bins["network"], bins["filter"]
    a, b = bins["rmse"][net][i], bins["rmse"][ref][i]
    if a is None or b is None or a <= b:
        return None
    return (f"note: this data's median scan interval is {median:.3g} s; at scans of {edges[i]:g}-{edges[i + 1]:g} s "
            f"{whose} {a / b:.2f}x {ref} ({a:.3f} m against {b:.3f} on {bins['data']}, their provenance): "
            f"--method {ref} may track these scans better")


def bank_note(intervals) -> str | None:
    """The shipped bank's note: ``interval_note`` of the general network's provenance, where the median of
    ``intervals`` lies in a bin that has the general network behind its filter; None elsewhere, and where the general
    network gives way to another member (``immnet.tracking.bank.DEFER``). Where another member of
    the bank (``immnet.tracking.bank.DEFAULT_MEMBERS``) takes these scans and its provenance measured it ahead of that
    filter, the note says so too, of the first such member (one trained at these scans first: ``real-11s`` at 10-12 s,
    ``real-4.5-12s`` at 8-10 s, each on real flights), so that the user, who knows which motion the data holds, has
    both measurements."""
    from immnet.tracking.bank import DEFAULT_MEMBERS, DEFER

    median = _median(intervals)
    if median is None:
        return None
    if any(_takes(_table_scans(m), median) for m in DEFER.get(GENERAL, ())):
        return None  # the general network gives way there (the 3D-LAST network's 1 s): the bank does not run it
    general = load_provenance(shipped(GENERAL))
    provs = {m: load_provenance(shipped(m)) or {} for m in DEFAULT_MEMBERS if m != GENERAL}
    others = [m for m, prov in provs.items() if _takes(prov, median)]
    note = interval_note(general, intervals, "the bank's general network was" if others else
                         "the bank's general network (its one member at these scans) was")
    if note is None:
        return None
    ref = general["interval_bins"]["filter"]
    # one measurement: of a member trained at these scans before one that takes them as longer ones cut by missed scans
    for name in sorted(others, key=lambda m: _span(provs[m], median) is None):
        found = _ahead(provs[name].get("tests", {}).items(), registry_name(name), ref)
        if found:
            set_name, a, b = found
            return note + (f"; {name!r}, which the bank runs beside it at these scans, tracked {what(set_name)} "
                           f"better than {ref} ({a:.3f} m against {b:.3f}, its provenance)")
    return note


def registry_name(name: str) -> str:
    """The ``immnet evaluate`` name of the shipped network ``name`` (``immnet.checkpoints.SHIPPED``): ``immnet`` for
    ``3dlast``, ``immnet-NAME`` for the others (``configs/methods/``)."""
    return "immnet" if name == "3dlast" else f"immnet-{name}"


def what(set_name: str) -> str:
    """A provenance's test set as a note names it: ``real flights (quickstart-5s)`` for the real-flight sets."""
    return f"real flights ({set_name})" if set_name.startswith("quickstart") else set_name


def weights_note(loaded, provenance: dict | None, intervals) -> str | None:
    """With the general weights loaded (the file ``loaded``, its ``provenance`` as ``load_provenance`` read it), a note
    (one line) where another shipped network was trained for the median of ``intervals`` (seconds; its provenance's
    ``interval_range``, or its one ``scan_interval``) and a provenance, its own or the general one's, measured it ahead
    of the general network on one test set, both in one run there; None otherwise (other weights loaded, no such
    network, no intervals)."""
    median, mine = _median(intervals), provenance or {}
    if Path(loaded).resolve() != shipped(GENERAL).resolve() or median is None:
        return None
    for name in (n for n in SHIPPED if n != GENERAL):
        prov = load_provenance(shipped(name)) or {}
        span = _span(prov, median)
        if span is None:
            continue
        found = _ahead([*prov.get("tests", {}).items(), *mine.get("tests", {}).items()], registry_name(name),
                       registry_name(GENERAL))
        if found:
            set_name, a, b = found
            scans = f"{span[0]:g}-{span[1]:g} s" if span[0] != span[1] else f"{span[0]:g} s"
            return (f"note: this data's median scan interval is {median:.3g} s; the shipped weights {name!r} were "
                    f"trained for scans of {scans} and tracked {what(set_name)} better ({a:.3f} m against the general "
                    f"one's {b:.3f}, their provenance): --weights {name} may track these scans better")
    return None


RADAR_BANDS = (("immnet-radar-5s", "radar-imm-robust-5s", (4.5, 5.5)),
               ("immnet-radar-11s", "radar-imm-robust-11s", (10.0, 12.0)))
"""The default tracker of CSV rows that carry each detection's covariance (a radar's plots with their stds, or the
``r_xx..r_zz`` columns), per scan band: the shipped network told each plot's covariance for those scans and the
model-based filter it is built on (the joint IMM told each plot's covariance, Huber's update; docs/radar.md)."""


def radar_default(intervals) -> tuple[str, str]:
    """``(method, line)``: the registry method that tracks CSV rows with each detection's covariance by default, from
    their scan ``intervals`` (s, every track's together: :func:`track_intervals`), and the line ``immnet track`` says
    on stderr. The shipped radar network of the band (``RADAR_BANDS``) that takes every interval (a longer gap cut
    into missed scans); where none does (scans between or outside the bands, or a track with an interval shorter than
    its band), the model-based filter of the band nearer the median interval (on the bands' ends), which takes any
    interval: the radar networks were trained only at their band's scans, and on plots the filter told each plot's
    covariance was measured ahead of the bank, which is not told it (docs/radar.md)."""
    median = _median(intervals)
    if median is None:  # no track of two rows: any band's network takes one scan; the first band's
        net, _, span = RADAR_BANDS[0]
        return net, (f"note: the rows carry each detection's covariance: tracked by {net}, the shipped network told "
                     f"each plot's covariance (no track has two rows to read a scan interval from; --method or "
                     f"--weights bank chooses another tracker)")
    for net, _, span in RADAR_BANDS:
        if span[0] - 1e-6 * span[1] <= median <= span[1] * (1 + 1e-6) and _accepts(span, None, intervals).all():
            return net, (f"note: the rows carry each detection's covariance and their median scan interval is "
                         f"{median:.3g} s: tracked by {net}, the shipped network told each plot's covariance for "
                         f"{span[0]:g}-{span[1]:g} s scans (--method or --weights bank chooses another tracker)")
    distance = [max(span[0] - median, median - span[1], 0.0) for _, _, span in RADAR_BANDS]
    net, filt, span = RADAR_BANDS[int(np.argmin(distance))]
    bands = ", ".join(f"{s[0]:g}-{s[1]:g} s" for _, _, s in RADAR_BANDS)
    why = f"whose scans the shipped radar networks ({bands}) were not trained at"
    if distance[int(np.argmin(distance))] == 0:  # the band's network refuses an interval: the shortest, or a longer one
        dt = np.unique(np.asarray(intervals, dtype=np.float64))  # that missed scans cut below the band
        refused = float(dt[~_accepts(span, None, dt)][0])
        cut = math.ceil(refused / (span[1] * (1 + 1e-6)))
        why = (f"but their shortest, {refused:.3g} s, is below {span[0]:g}-{span[1]:g} s, where {net} was trained"
               if refused == dt[0] else f"but an interval of {refused:.3g} s, {cut} scans of {refused / cut:.3g} s "
               f"with missed scans, is below {span[0]:g}-{span[1]:g} s, where {net} was trained")
    return filt, (f"note: the rows carry each detection's covariance and their median scan interval is {median:.3g} s, "
                  f"{why}: tracked by {filt}, the "
                  f"model-based filter told each plot's covariance tuned at {span[0]:g}-{span[1]:g} s scans, which "
                  f"takes any interval (--method or --weights bank chooses another tracker)")
