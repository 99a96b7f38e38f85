"""Run methods over a data set in batches and score them (``evaluate``)."""

from __future__ import annotations

import sys
import time
from typing import Mapping, Sequence

import torch
from tensordict import TensorDict
from tqdm import tqdm

from immnet import keys
from immnet.evaluation.metrics import MetricAccumulator
from immnet.evaluation.methods import missing_keys


def _as_mapping(methods) -> dict:
    if isinstance(methods, Mapping):
        return dict(methods)
    return {m.name: m for m in methods}


def evaluate(
    methods: Mapping[str, object] | Sequence[object],
    data: TensorDict,
    batch_size: int = 256,
    progress: bool = True,
    keep: Sequence[int] = (),
) -> dict[str, dict]:
    """Every method over ``data`` (``TensorDict [N]``), in batches of ``batch_size``, under ``no_grad``.

    Returns ``{name: result}``, ``result`` holding the metrics of
    :meth:`MetricAccumulator.compute`, ``seconds`` (wall time inside ``track``, summed over
    batches) and ``kept``: the outputs (``state``, ``mode_probs`` if any) of the trajectories
    at indices ``keep`` (in sorted order), for case-study figures. Needs ground-truth ``states``; ``mode`` enables
    the post-switch RMSE and, with ``mode_probs``, the mode accuracy and confusion.
    """
    methods = _as_mapping(methods)
    if keys.STATES not in data.keys():
        raise ValueError("evaluation needs ground-truth 'states' in the data to score the estimates")
    for name, method in methods.items():
        missing = missing_keys(method, list(data.keys()))
        if missing:
            raise ValueError(f"method {name!r} needs {', '.join(missing)}, which the data lacks")
        if callable(getattr(method, "check", None)):
            method.check(data)  # e.g. a learned tracker refusing another dt: before any method runs
    has_mode = keys.MODE in data.keys()
    n = data.batch_size[0]
    keep = sorted(set(keep))
    results = {}
    for name, method in methods.items():
        acc = MetricAccumulator()
        seconds = 0.0
        kept: dict[str, list[torch.Tensor]] = {}
        bar = tqdm(
            range(0, n, batch_size), desc=f"{name:>14}", unit="batch", file=sys.stderr,
            disable=not progress, leave=True,
        )
        for start in bar:
            batch = data[start : start + batch_size]
            t0 = time.perf_counter()
            with torch.no_grad():
                out = method.track(batch)
            seconds += time.perf_counter() - t0
            state = out[keys.STATE]
            probs = out.get(keys.MODE_PROBS, None)
            mode = batch[keys.MODE] if has_mode else None
            acc.update(state, batch[keys.STATES], mode, probs)
            local = [i - start for i in keep if start <= i < start + batch.batch_size[0]]
            if local:
                kept.setdefault(keys.STATE, []).append(state[local].detach().cpu())
                if probs is not None:
                    kept.setdefault(keys.MODE_PROBS, []).append(probs[local].detach().cpu())
        result = acc.compute()
        result["seconds"] = seconds
        result["kept"] = {k: torch.cat(v) for k, v in kept.items()}
        results[name] = result
    return results


def to_json(results: Mapping[str, dict]) -> dict[str, dict]:
    """The JSON view of :func:`evaluate`'s results: scalars only (no curves, no kept outputs)."""
    out = {}
    for name, r in results.items():
        row = {
            "rmse": r["rmse"],
            "rmse_pooled": r["rmse_pooled"],
            "rmse_post_switch": r["rmse_post_switch"],
            "seconds": round(r["seconds"], 4),
        }
        if r.get("mode_accuracy") is not None:
            row["mode_accuracy"] = r["mode_accuracy"]
            row["confusion"] = r["confusion"].tolist()
        out[name] = row
    return out
