"""Tuning a model-based method on training data: a coordinate search over knobs of its configuration.

A search is a YAML file (``configs/tuning/*.yaml``, docs/baselines.md "Filters for real flights")::

    method:                      # a method config, as in configs/methods/: the starting setting
      class_path: immnet.filters.per_axis.PerAxisIMMTracker
      init_args: {name: real-imm-axis, r: data, sigma_q: [0.05, 0.5], p_stay: 0.98, model_set: {...}}
    grid:                        # dotted paths into init_args (list items by index) -> values to try
      sigma_q.0: [0.02, 0.05, 0.1]
      model_set.models.1.init_args.vertical: [0.1, 0.3, 1.0]
      sigma_q.2,sigma_q.3: [0.5, 1.0]   # one knob of several paths (comma-separated): each takes the value

From the method as written, ``coordinate_search`` sweeps each knob in turn with the others held at the best
so far, and repeats the sweep until a full pass changes nothing (at most ``max_passes``); a setting already
scored is not run again. The score is ``immnet evaluate``'s Average RMSE over its scored scans; on several data
sets (a mixture: 3D-LAST and real flights, 1 s and 5 s scans, whose errors differ tenfold) the **geometric mean**
of each set's Average RMSE, so that each set counts by its relative error and none by its scale. The winner is
written as a method config (``configs/methods/NAME.yaml``) with the search, its data and its score in the
header. The data must be training or validation data: a set whose ``meta.json`` names it a test split is
refused.
"""

from __future__ import annotations

import copy
import datetime
import math
import sys
import time
from pathlib import Path
from typing import Callable

import torch
import yaml
from tensordict import TensorDict

from immnet import keys
from immnet.config import instantiate, load_yaml
from immnet.evaluation.metrics import position_error, rmse, scored_mask


def coordinate_search(score: Callable[[dict], float], grid: dict, start: dict, max_passes: int = 2,
                      progress: bool = True, tag: str = "search") -> tuple[dict, float, list[dict]]:
    """Minimize ``score(setting)`` knob by knob over ``grid`` from ``start``; returns the best setting, its
    score and every scored setting (``{**setting, "score", "seconds"}``), best first."""
    cache: dict[tuple, float] = {}
    table: list[dict] = []

    def run(setting: dict) -> float:
        key = tuple(repr(setting[k]) for k in grid)
        if key not in cache:
            t0 = time.perf_counter()
            cache[key] = score(setting)
            table.append({**setting, "score": cache[key], "seconds": round(time.perf_counter() - t0, 2)})
            if progress:
                print(f"[{tag}] {len(table):3d} {setting} -> {cache[key]:.4f} m", file=sys.stderr, flush=True)
        return cache[key]

    best, best_score = dict(start), run(start)
    for _ in range(max_passes):
        changed = False
        for knob, values in grid.items():
            for v in values:
                trial = {**best, knob: v}
                s = run(trial)
                if s < best_score - 1e-9:
                    best, best_score, changed = trial, s, True
        if not changed:
            break
    return best, best_score, sorted(table, key=lambda row: row["score"])


def average_rmse(method, batch: TensorDict) -> float:
    """Average RMSE (m) of ``method`` on ``batch`` over the scans ``immnet evaluate`` scores (``scored_mask``)."""
    with torch.no_grad():
        return states_rmse(method.track(batch)[keys.STATE], batch)


def states_rmse(state: torch.Tensor, batch: TensorDict) -> float:
    """Average RMSE (m) of estimates ``state [B, T, 9]`` of ``batch``'s tracks, as ``average_rmse``."""
    mask = scored_mask(batch[keys.STATES], batch[keys.MEASUREMENTS])
    return rmse(position_error(state, batch[keys.STATES]), mask)["avg"]


def geometric_mean(scores) -> float:
    """``(prod scores)^(1/n)``: each score counts by its relative size, none by its scale (module doc)."""
    scores = list(scores)
    return math.exp(sum(math.log(s) for s in scores) / len(scores))


def mixture_rmse(method, sets) -> float:
    """``average_rmse`` of ``method`` on one batch, or the geometric mean of it over a list of batches (module doc)."""
    if isinstance(sets, TensorDict):
        return average_rmse(method, sets)
    return geometric_mean(average_rmse(method, batch) for batch in sets)


def score_name(sets: int) -> str:
    """What ``mixture_rmse`` is on ``sets`` data sets, as the tune command and a tuned config's header say it."""
    return "Average RMSE" if sets == 1 else f"geometric mean of the {sets} sets' Average RMSE"


def _walk(config, path: str):
    """The container holding the last part of dotted ``path`` in ``config`` and that part (index or key)."""
    *head, last = path.split(".")
    node = config
    for part in head:
        node = node[int(part)] if isinstance(node, list) else node[part]
    return node, (int(last) if isinstance(node, list) else last)


def get_path(config: dict, path: str):
    node, last = _walk(config, path)
    return node[last]


def set_path(config: dict, path: str, value) -> dict:
    """A copy of ``config`` with the value at dotted ``path`` (list items by index) replaced."""
    out = copy.deepcopy(config)
    node, last = _walk(out, path)
    if isinstance(node, list) and not 0 <= last < len(node) or isinstance(node, dict) and last not in node:
        raise KeyError(path)
    node[last] = value
    return out


class Search:
    """A search file: ``method`` (a config with ``class_path`` / ``init_args``) and ``grid`` (dotted paths into
    ``init_args`` -> values)."""

    def __init__(self, method: dict, grid: dict, max_passes: int = 2):
        if not isinstance(method, dict) or "class_path" not in method:
            raise ValueError("a search needs 'method': a config with class_path and init_args")
        if not isinstance(grid, dict) or not grid:
            raise ValueError("a search needs 'grid': dotted paths into the method's init_args -> values to try")
        self.method, self.grid, self.max_passes = method, grid, int(max_passes)
        args = method.get("init_args") or {}
        for knob, values in grid.items():
            for path in knob.split(","):
                try:
                    get_path(args, path)
                except (KeyError, IndexError, ValueError, TypeError):
                    raise ValueError(f"grid knob {path!r} is not a path into the method's init_args") from None
            if not isinstance(values, list) or not values:
                raise ValueError(f"grid knob {knob!r} needs a non-empty list of values, got {values!r}")

    @classmethod
    def from_yaml(cls, path) -> "Search":
        spec = load_yaml(path)
        if not isinstance(spec, dict):
            raise ValueError(f"{path}: a search file is a mapping with 'method' and 'grid'")
        return cls(spec.get("method"), spec.get("grid"), spec.get("max_passes", 2))

    @property
    def start(self) -> dict:
        args = self.method.get("init_args") or {}
        return {knob: get_path(args, knob.split(",")[0]) for knob in self.grid}

    def config(self, setting: dict) -> dict:
        """The method config of one setting."""
        args = copy.deepcopy(self.method.get("init_args") or {})
        for knob, value in setting.items():
            for path in knob.split(","):
                args = set_path(args, path, value)
        return {"class_path": self.method["class_path"], "init_args": args}

    def run(self, data, progress: bool = True, score: Callable | None = None) -> dict:
        """The search on ``data`` (a batch, or a list of batches scored by ``mixture_rmse``): ``{"best", "score",
        "config", "table"}``. ``score``: a setting's method -> its score, in place of ``mixture_rmse`` on ``data``
        (``immnet tune --scenes``: the multi-target tracker's mean GOSPA)."""
        if score is None:
            for batch in [data] if isinstance(data, TensorDict) else data:
                if keys.STATES not in batch.keys():
                    raise ValueError("a search needs 'states' (ground truth) in its data to score settings")
            score = lambda method: mixture_rmse(method, data)  # noqa: E731
        name = (self.method.get("init_args") or {}).get("name", "search")
        best, value, table = coordinate_search(lambda s: score(instantiate(self.config(s))),
                                               self.grid, self.start, self.max_passes, progress, tag=name)
        return {"best": best, "score": value, "config": self.config(best), "table": table}

    def write(self, result: dict, out, search_path, data_desc: str, n: int, score_desc: str, command: str = "",
              what: str = "tracks, never a test split") -> Path:
        """Write the best setting's method config to ``out``, named after its file (the registry's name);
        ``score_desc``: what the score is (``score_name``'s, or the multi-target tracker's GOSPA); ``command``: the
        tune command's options beside ``--search`` (as a reader reruns it); ``what``: the data's unit."""
        out = Path(out)
        config = {**result["config"], "init_args": {**result["config"]["init_args"], "name": out.stem}}
        header = [
            f"# Tuned by `immnet tune --search {search_path}{command}` on {data_desc} ({n} {what}):",
            f"# coordinate search over {self.grid} ({len(result['table'])} settings scored);",
            f"# {score_desc} {result['score']:.4f} m there; {datetime.date.today().isoformat()}. Do not edit by hand.",
        ]
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text("\n".join(header) + "\n" + yaml.safe_dump(config, sort_keys=False))
        return out
