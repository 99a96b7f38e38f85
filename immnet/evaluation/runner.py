"""Run methods over a data set in batches and score them (``evaluate``); their JSON view (``to_json``).

Where the data enter, every batch's measurements pass :func:`immnet.data.validate.gate_measurements`:
a measurement no sensor could report (non-finite, or beyond ``max_position`` metres) becomes a
missed detection before any method sees it, and is counted (docs/evaluation.md).
"""

from __future__ import annotations

import math
import sys
import time
from typing import Mapping, Sequence

import torch
from tensordict import TensorDict

from immnet import keys
from immnet.data.times import scan_intervals
from immnet.data.validate import MAX_ABS_POSITION, check_limit, gate_measurements
from immnet.evaluation.metrics import MetricAccumulator
from immnet.filters.methods import missing_keys
from immnet.progress import progress as progress_bar


def _as_mapping(methods) -> dict:
    if isinstance(methods, Mapping):
        return dict(methods)
    return {m.name: m for m in methods}


def check_method(name: str, method, data_keys, data: TensorDict | None = None) -> None:
    """A ValueError where ``method`` cannot run on the data: an array it needs is not among ``data_keys``, or its
    ``check(data)`` (where it has one and ``data`` is given; e.g. a learned tracker refusing another dt) refuses."""
    missing = missing_keys(method, data_keys)
    if missing:
        raise ValueError(f"method {name!r} needs {', '.join(missing)}, which the data lacks")
    if data is not None and callable(getattr(method, "check", None)):
        method.check(data)


def evaluate(
    methods: Mapping[str, object] | Sequence[object],
    data: TensorDict,
    batch_size: int = 256,
    progress: bool = True,
    keep: Sequence[int] = (),
    max_position: float = MAX_ABS_POSITION,
) -> dict[str, dict]:
    """Every method over ``data`` (``TensorDict [N]``), in batches of ``batch_size``, under ``no_grad``.

    Returns ``{name: result}``, ``result`` holding the metrics of
    :meth:`MetricAccumulator.compute`, ``seconds`` (wall time inside ``track``, summed over
    batches) and ``kept``: the outputs (``state``, ``mode_probs`` if any) and the gated
    ``measurements`` of the trajectories at indices ``keep`` (in sorted order), for case-study
    figures, and ``gated``: how many
    measurements were beyond what a sensor reports (non-finite, or ``|z_a| > max_position`` m) and
    were given to every method as missed detections. Needs ground-truth ``states``; ``mode``
    enables the post-switch RMSE and, with ``mode_probs``, the mode accuracy and confusion.
    """
    methods = _as_mapping(methods)
    max_position = check_limit(max_position)
    if keys.STATES not in data.keys():
        raise ValueError("evaluation needs ground-truth 'states' in the data to score the estimates")
    for name, method in methods.items():
        check_method(name, method, list(data.keys()), data)  # before any method runs
    has_mode = keys.MODE in data.keys()
    n = data.batch_size[0]
    keep = sorted(set(keep))
    results = {}
    for name, method in methods.items():
        acc = MetricAccumulator()
        seconds, gated = 0.0, 0
        kept: dict[str, list[torch.Tensor]] = {}
        bar = progress_bar(
            range(0, n, batch_size), desc=f"{name:>14}", unit="batch", file=sys.stderr,
            disable=not progress, leave=True,
        )
        for start in bar:
            batch = data[start : start + batch_size]
            z, n_gated = gate_measurements(batch[keys.MEASUREMENTS], max_position)
            gated += n_gated
            batch = TensorDict({**dict(batch.items()), keys.MEASUREMENTS: z}, batch_size=batch.batch_size,
                               device=batch.device)
            t0 = time.perf_counter()
            with torch.no_grad():
                out = method.track(batch)
            seconds += time.perf_counter() - t0
            state = out[keys.STATE]
            probs = out.get(keys.MODE_PROBS, None)
            mode = batch[keys.MODE] if has_mode else None
            acc.update(state, batch[keys.STATES], mode, probs, measurements=z,
                       intervals=scan_intervals(batch) if has_mode else None)  # the post-switch window in s
            local = [i - start for i in keep if start <= i < start + batch.batch_size[0]]
            if local:
                kept.setdefault(keys.STATE, []).append(state[local].detach().cpu())
                kept.setdefault(keys.MEASUREMENTS, []).append(z[local].cpu())  # as the method saw them
                if probs is not None:
                    kept.setdefault(keys.MODE_PROBS, []).append(probs[local].detach().cpu())
        results[name] = {**acc.compute(), "seconds": seconds, "gated": gated,
                         "kept": {k: torch.cat(v) for k, v in kept.items()}}
    return results


def evaluate_by_interval(methods, data: TensorDict, edges):
    """Each method's RMSE by scan interval on ``data`` (``metrics.rmse_by_interval`` over the scans :func:`evaluate`
    scores, the bins of ``metrics.interval_bin``), one method at a time as it is tracked (float64): yields
    ``(name, [pooled "avg" RMSE or None per bin])``, then ``("scans", [scored scans per bin])``."""
    from immnet.data.storage import as_batch
    from immnet.evaluation.metrics import interval_bin, position_error, rmse_by_interval, scored_mask

    batch = as_batch(data, torch.float64)
    dt = scan_intervals(batch, torch.float64, None)
    mask = scored_mask(batch[keys.STATES], batch[keys.MEASUREMENTS])
    which = interval_bin(dt, edges)  # checks the edges before any method runs
    for name, method in _as_mapping(methods).items():
        with torch.no_grad():
            err = position_error(method.track(batch)[keys.STATE], batch[keys.STATES])
        yield name, rmse_by_interval(err, dt, edges, mask)
    yield "scans", [int((mask & (which == i)).sum()) for i in range(len(edges) - 1)]


def finite_or_none(x):
    """``x`` with every float that is not finite replaced by ``None`` (JSON's ``null``), through
    dicts, lists and tuples: what ``json.dumps(..., allow_nan=False)`` accepts."""
    if isinstance(x, Mapping):
        return {k: finite_or_none(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [finite_or_none(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def to_json(results: Mapping[str, dict]) -> dict[str, dict]:
    """The JSON view of :func:`evaluate`'s results: scalars only (no curves, no kept outputs), a
    missing or non-finite number as ``None``. ``nan_scans`` / ``diverged``: scored scans with a
    non-finite estimate and the trajectories holding them (the RMSEs are then ``None``)."""
    out = {}
    for name, r in results.items():
        c = r.get("counts", {})
        row = {
            "rmse": r["rmse"],
            "rmse_pooled": r["rmse_pooled"],
            "rmse_post_switch": r["rmse_post_switch"],
            "seconds": round(r["seconds"], 4),
            "nan_scans": c.get("nan_scans", 0),
            "diverged": c.get("diverged", 0),
        }
        if r.get("mode_accuracy") is not None:
            row["mode_accuracy"] = r["mode_accuracy"]
            row["confusion"] = r["confusion"].tolist()
        out[name] = finite_or_none(row)
    return out
