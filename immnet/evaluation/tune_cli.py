"""``immnet tune``: tune a model-based method's configuration on training data (``immnet.evaluation.search``).

    immnet tune --search configs/tuning/real-imm-axis.yaml --data data/real/quickstart/train \\
        --out configs/methods/real-imm-axis.yaml
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def register(subparsers) -> None:
    t = subparsers.add_parser("tune", help="tune a model-based method (a search file) on training data",
                              description="Coordinate search over the knobs of a search file (configs/tuning/) on "
                                          "a training or validation data set; writes the winner's method config.")
    t.add_argument("--search", required=True, help="a search file (configs/tuning/*.yaml)")
    given = t.add_mutually_exclusive_group(required=True)
    given.add_argument("--data", nargs="+",
                       help="data set directories or .npz files to tune on, taken whole (never a test split); several: "
                            "the geometric mean of each set's Average RMSE is the score")
    given.add_argument("--scenes", nargs="+",
                       help="multi-target scene sets (immnet data scenes) whose training scenes score a per-track "
                            "filter: the mean GOSPA of the multi-target tracker with it (its other settings its "
                            "defaults); a set's test scenes are never read; several: the geometric mean")
    t.add_argument("--out", type=Path, required=True, help="the method config to write (configs/methods/NAME.yaml)")
    t.add_argument("--limit", type=int, help="only the first N tracks (training scenes) of each set")
    t.add_argument("--quiet", action="store_true", help="no line per scored setting")
    t.set_defaults(func=run_tune)


def tuning_data(paths, limit: int | None = None):
    """The tracks of ``paths`` (whole data sets) as float64 batches: one batch for one set, a list of them for
    several (scored each apart, ``immnet.evaluation.search.mixture_rmse``); a set whose ``meta.json`` says it is a
    test split is refused (tuning there would make its table a fit)."""
    import torch

    from immnet.data.storage import as_batch, load_dataset

    parts = []
    for path in paths:
        td, meta = load_dataset(path)
        if str((meta or {}).get("split", "")).lower() == "test":
            raise ValueError(f"{path} is a test split (meta.json 'split': 'test'): tune on training or validation data")
        td = td[: limit] if limit else td
        parts.append(as_batch(td, torch.float64))
    return parts if len(parts) > 1 else parts[0]


def tuning_scenes(paths, limit: int | None = None) -> list[list]:
    """The training scenes (split ``train``) of each scene set in ``paths``, the first ``limit`` of each; a set's test
    scenes are never read, and a set without training scenes is refused."""
    from immnet.data.scenes import load_index, load_scene

    sets = []
    for path in map(Path, paths):
        entries = [e for e in load_index(path)["scenes"] if e["split"] == "train"][:limit or None]
        if not entries:
            raise ValueError(f"{path}: no training scenes (split train) to tune on")
        sets.append([load_scene(path / e["file"]) for e in entries])
    return sets


def scene_score(args):
    """``(score, n, what the score is)`` of ``immnet tune --scenes``: a setting's method -> the multi-target tracker's
    mean GOSPA with it as the per-track filter on the sets' training scenes (the geometric mean over sets), and the
    number of those scenes."""
    from immnet.evaluation.scenes import tracker_gospa
    from immnet.evaluation.search import geometric_mean
    from immnet.filters.multi import TrackFilter

    sets = tuning_scenes(args.scenes, args.limit)
    desc = ("mean GOSPA" if len(sets) == 1 else f"geometric mean of the {len(sets)} sets' mean GOSPA") + \
        " (c 200 m, p 2) of the multi-target tracker"

    def score(method) -> float:
        return geometric_mean(tracker_gospa(scenes, lambda: TrackFilter.of_method(method, method.name))
                              for scenes in sets)

    return score, sum(map(len, sets)), desc


def run_tune(args) -> int:
    from immnet.evaluation.runner import finite_or_none
    from immnet.evaluation.search import Search, score_name

    search = Search.from_yaml(args.search)
    if args.scenes:
        given, data, (score, n, desc) = args.scenes, None, scene_score(args)
        unit, what, command = "training scenes", "training scenes, never a test scene", " --scenes " + " ".join(given)
    else:
        given, data, score = args.data, tuning_data(args.data, args.limit), None
        sets = data if isinstance(data, list) else [data]
        n, desc = sum(batch.batch_size[0] for batch in sets), score_name(len(sets))
        unit, what, command = "tracks", "tracks, never a test split", ""
    print(f"tuning {args.search} on {n} {unit} of {', '.join(map(str, given))} ({desc})", file=sys.stderr)
    result = search.run(data, progress=not args.quiet, score=score)
    out = search.write(result, args.out, args.search, ", ".join(map(str, given)), n, desc, command, what)
    print(json.dumps(finite_or_none({k: result[k] for k in ("best", "score")}), indent=2, default=str, allow_nan=False))
    print(f"wrote {out}", file=sys.stderr)
    return 0
