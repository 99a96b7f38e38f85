"""``immnet evaluate`` (score methods on a data set) and ``immnet tune-imm`` (the IMM-Tuned search).

    immnet evaluate --data /tmp/eval1k --split all --json results.json --figures figs/
    immnet tune-imm --data data/train
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from immnet.evaluation import wandb_log
from immnet.filters.registry import configured_methods


def register(subparsers) -> None:
    p = subparsers.add_parser("evaluate", help="score tracking methods on a data set (RMSE table, JSON, figures)",
                              description="Score tracking methods on a 3D-LAST data set: RMSE table, JSON, figures.")
    p.add_argument("--data", required=True,
                   help="a data set directory (immnet data generate) or an .npz file; or a scene set (immnet data "
                        "scenes), whose scenes the multi-target tracker runs on, scored by GOSPA (docs/evaluation.md, "
                        "\"Scenes\")")
    p.add_argument("--split", choices=("test", "all"), default="test",
                   help="test: the DataModule's test split of a generated directory, a scene set's held-out scenes "
                        "(default); all: every trajectory or scene (an .npz is always taken whole)")
    p.add_argument("--methods", metavar="NAME,...",
                   help="comma-separated method names (default: every available one the data allows), of: "
                        f"{', '.join(configured_methods())} (the built-in and each configs/methods/NAME.yaml, the "
                        "working directory's and the packaged ones: docs/configs.md); on a scene set: the multi-target "
                        "tracker's per-track filters (model-based IMMs and Kalman filters; default: the tracker's "
                        "default filter), each also told the association")
    p.add_argument("--associator", choices=("gnn", "jpda"), default=None,
                   help="scene sets only: the multi-target tracker's association (default gnn)")
    p.add_argument("--checkpoint", action="append", default=[], metavar="[NAME=]CKPT",
                   help="checkpoint for a neural method; a bare path goes to every selected method that takes one")
    p.add_argument("--guard", default="checkpoint",
                   help="range guard of the methods that have one (immnet, imm-ekf-guard, imm-ekf-guard-sticky): "
                        "'checkpoint' (as configured: 3D-LAST's region, turns back beyond 33 km and within 4 km), "
                        "'none' (data from another region; imm-ekf-guard becomes imm-ekf's twin), or 'OUTER,INNER' "
                        "in metres (another region, 3D-LAST's speed envelope); as `immnet track --guard`")
    p.add_argument("--told-r", action="store_true",
                   help="every IMMNet is told each track's measurement std from the data (its 'r'), as the model-based "
                        "filters for real flights are, instead of estimating it from the measurements")
    p.add_argument("--sigma-q", type=float, default=None, metavar="SIGMA_Q",
                   help="the truth's process noise (m/s^2) for the clairvoyant references (default: the data's "
                        "meta.json spec; 3D-LAST's 0.2 for an .npz)")
    p.add_argument("--batch-size", type=int, default=None, help="trajectories per batch (default 256)")
    p.add_argument("--limit", type=int, help="only the first N trajectories (scenes, of a scene set) of the split")
    p.add_argument("--max-position", type=float, default=None, metavar="M",
                   help="a measurement with a component beyond M metres from the radar (or not finite) is "
                        "beyond what a sensor reports: it is treated as a missed detection, counted and "
                        "reported (default 1e7; inf turns the limit off, non-finite ones are still gated)")
    p.add_argument("--json", type=Path, help="write the results as JSON here")
    p.add_argument("--markdown", type=Path, help="write the table as Markdown here (for a README)")
    p.add_argument("--figures", type=Path, metavar="DIR", help="write the PNG figures into DIR")
    p.add_argument("--seed", type=int, default=0, help="picks the case-study trajectories of --figures (default 0)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    wandb_log.add_arguments(p)
    p.set_defaults(func=run_evaluate)

    t = subparsers.add_parser("tune-imm", help="search the IMM-Tuned configuration on validation data",
                              description="Choose IMM-Tuned's model set and sigma_q on the validation split "
                                          "(never the test split) and write its method config.")
    t.add_argument("--data", required=True, help="a data set directory or an .npz file")
    t.add_argument("--split", choices=("val",), default="val", help="only the validation split is allowed")
    t.add_argument("--n", type=int, default=500, help="validation trajectories used (the first N; default 500)")
    t.add_argument("--out", type=Path, default=None,
                   help="config to write (default: configs/methods/imm-tuned.yaml of the checkout the package runs "
                        "from; for an installed package, of the working directory, where `immnet evaluate` "
                        "looks first: docs/configs.md)")
    t.set_defaults(func=run_tune)


# --- data -------------------------------------------------------------------------------------
def load_split(path, split: str, limit: int | None = None):
    """``(TensorDict [N], meta)``: the named split of a data set (see docs/evaluation.md)."""
    from immnet.data.storage import load_dataset

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"data not found: {path}")
    data, meta = load_dataset(path)
    if split != "all" and path.is_dir():
        from immnet.data.datamodule import LASTDataModule

        data = LASTDataModule(path).split(split)
    return _first(data, limit), meta


def _first(items, limit: int | None):
    """The first ``limit`` of ``items`` (``--limit``; None: all); a ValueError unless it is positive."""
    if limit is None:
        return items
    if limit < 1:
        raise ValueError("--limit must be positive")
    return items[:limit]


def _method_names(requested: str | None) -> list[str]:
    """The names of ``--methods`` (comma-separated; None: not given, no names); a ValueError where it names none."""
    names = [n.strip() for n in (requested or "").split(",") if n.strip()]
    if requested is not None and not names:
        raise ValueError("--methods is empty")
    return names


def pick_cases(data, n: int = 2, seed: int = 0) -> list[int]:
    """``n`` trajectory indices drawn with ``seed``, preferring ones with at least two switches."""
    import torch

    from immnet import keys
    from immnet.evaluation.metrics import switch_steps

    N = data.batch_size[0]
    g = torch.Generator().manual_seed(seed)
    order = torch.randperm(N, generator=g)
    if keys.MODE in data.keys():
        n_sw = switch_steps(data[keys.MODE]).sum(dim=-1)[order]
        order = order[torch.argsort(-(n_sw.clamp(max=2)), stable=True)]
    return sorted(order[:n].tolist())


# --- methods ----------------------------------------------------------------------------------
def _checkpoints(specs: list[str], names: list[str]) -> dict[str, str]:
    from immnet.filters.methods import takes_checkpoint

    named, bare = {}, []
    for s in specs:
        name, sep, ck = s.partition("=")
        if sep and name in names:
            named[name] = ck
        elif sep and not Path(s).exists():
            raise ValueError(f"--checkpoint {s}: {name!r} is not a selected method ({', '.join(names)})")
        else:
            bare.append(s)
    if len(bare) > 1:
        raise ValueError("give at most one bare --checkpoint; name the others as NAME=CKPT")
    if bare:
        takers = [n for n in names if n not in named and takes_checkpoint(n)]
        if not takers:
            raise ValueError(f"--checkpoint {bare[0]}: none of the selected methods ({', '.join(names)}) takes one")
        named.update({n: bare[0] for n in takers})
    return named


def _candidates(requested: str | None) -> list[str]:
    """The methods ``select_methods`` tries: ``--methods``' names, or every available method where it is not given."""
    from immnet.filters.methods import available_methods

    return _method_names(requested) if requested is not None else available_methods()


def select_methods(requested: str | None, checkpoints: list[str], data_keys, note=print, data=None,
                   meta: dict | None = None, guard="checkpoint", sigma_q: float | None = None,
                   told_r: bool = False) -> dict:
    """``{name: method}``: the requested names (errors are errors) or, by default, every available
    method that builds, whose ``needs`` the data meet and whose ``check(data)`` (where it has one
    and ``data`` is given) passes; the others skipped with a note. ``guard`` (default ``"checkpoint"``, ``AS_CONFIGURED``:
    each as configured) and ``told_r`` go to ``build_method``;
    a method with ``configure`` is told the data's ``meta`` and ``sigma_q`` (``--sigma-q``)."""
    from immnet.evaluation.runner import check_method
    from immnet.filters.methods import build_method

    explicit = requested is not None
    names = _candidates(requested)
    ckpt = _checkpoints(checkpoints, names)
    methods = {}
    for name in names:
        try:
            method = build_method(name, checkpoint=ckpt.get(name), guard=guard, told_r=told_r)
            check_method(name, method, data_keys, data)
        except (ValueError, FileNotFoundError, TypeError) as err:
            if explicit:
                raise
            note(f"note: skipping {name}: {err}")
            continue
        methods[name] = method
    if not methods:
        raise ValueError("no method to evaluate")
    told = [m for m in methods.values() if callable(getattr(m, "configure", None))]
    if sigma_q is not None and not told:
        raise ValueError(f"--sigma-q is for the clairvoyant references; none is selected ({', '.join(methods)})")
    for method in told:
        msg = method.configure(meta, sigma_q=sigma_q)
        if msg:
            note(f"note: {msg}")
    return methods


# --- what was scored -------------------------------------------------------------------------
def scan_summary(results) -> dict:
    """What the data left unscored, the same for every method (taken from the first): ``gated``
    measurements, ``scored`` / ``without_truth`` / ``before_first_detection`` scans, and the
    trajectories ``excluded`` for want of any scored scan (see docs/evaluation.md)."""
    first = next(iter(results.values()))
    c = first["counts"]
    keep = ("scans", "scored", "without_truth", "before_first_detection", "trajectories", "excluded")
    return {"gated": first["gated"], **{k: c[k] for k in keep}}


def scan_notes(scans: dict, results, limit: float) -> list[str]:
    """The notes on stderr: gated measurements, unscored scans, excluded and diverged trajectories."""
    notes = []
    if scans["gated"]:
        notes.append(f"note: {scans['gated']} measurements beyond what a sensor reports (not finite, or a "
                     f"component beyond {limit:g} m) were treated as missed detections")
    if scans["without_truth"] or scans["before_first_detection"]:
        notes.append(f"note: scored {scans['scored']} of {scans['scans']} scans: {scans['without_truth']} have no "
                     f"truth, {scans['before_first_detection']} come before their track's first detection")
    if scans["excluded"]:
        notes.append(f"note: {scans['excluded']} of {scans['trajectories']} trajectories have no scan to score "
                     f"(no truth, or no detection while there is truth) and are excluded")
    for name, r in results.items():
        c = r["counts"]
        if c["diverged"]:
            notes.append(f"note: {name}: the estimate is not finite at {c['nan_scans']} scored scans of "
                         f"{c['diverged']} trajectories (diverged): no RMSE is reported")
    return notes


# --- commands ---------------------------------------------------------------------------------
def run_evaluate(args) -> int:
    from immnet.data.validate import MAX_ABS_POSITION, check_limit
    from immnet.evaluation.runner import evaluate, to_json
    from immnet.evaluation.table import format_markdown, format_table
    from immnet.imm.guard import parse_guard

    if is_scene_set(args.data):
        return run_scenes(args)
    if args.associator is not None:
        raise ValueError(f"--associator is for scene sets (immnet data scenes); {args.data} is not one")
    limit = check_limit(MAX_ABS_POSITION if args.max_position is None else args.max_position)
    guard = parse_guard(args.guard)
    _check_outputs(args)
    data, meta = load_split(args.data, args.split, args.limit)
    note = lambda msg: print(msg, file=sys.stderr)  # noqa: E731
    methods = select_methods(args.methods, args.checkpoint, list(data.keys()), note, data, meta, guard, args.sigma_q,
                             args.told_r)
    if args.batch_size is None:
        args.batch_size = 256
    if args.batch_size < 1:
        raise ValueError("--batch-size must be positive")
    log = wandb_log.wanted(args.wandb)
    figures = args.figures
    if log and figures is None:  # the run holds the figures: written beside it
        import tempfile

        figures = Path(tempfile.mkdtemp(prefix="immnet-figures-"))
    cases = pick_cases(data, 2, args.seed) if figures else []
    split = "all" if Path(args.data).is_file() else args.split
    note(f"evaluating {', '.join(methods)} on {data.batch_size[0]} trajectories ({args.data}, split {split})")
    results = evaluate(methods, data, batch_size=args.batch_size, progress=not args.quiet, keep=cases,
                       max_position=limit)
    scans = scan_summary(results)
    for msg in scan_notes(scans, results, limit):
        note(msg)
    rows = to_json(results)
    print(format_table(rows))
    _write_text(args.markdown, format_markdown(rows), note)
    doc = {"n_trajectories": data.batch_size[0], "data": str(args.data), "split": split, "seed": args.seed,
           "guard": args.guard, "told_r": args.told_r, "max_position": limit, "scans": scans, "methods": rows}
    _write_json(args.json, doc, note)
    paths = []
    if figures:
        from immnet.evaluation.figures import write_figures

        paths = write_figures(results, data, cases, figures)
        if args.figures:
            note(f"wrote {len(paths)} figures to {args.figures} (case studies: trajectories {cases})")
    if log:
        log_run(args, results, rows, paths, data, meta, split, note)
        if not args.figures:
            import shutil

            shutil.rmtree(figures, ignore_errors=True)
    return 0


def is_scene_set(path) -> bool:
    """Whether ``path`` is a scene set of ``immnet data scenes`` (a directory holding its index)."""
    from immnet.data.scenes import INDEX

    return Path(path).is_dir() and (Path(path) / INDEX).is_file()


SCENE_REFUSED = (("checkpoint", "--checkpoint", []), ("guard", "--guard", "checkpoint"), ("told_r", "--told-r", False),
                 ("sigma_q", "--sigma-q", None), ("batch_size", "--batch-size", None),
                 ("max_position", "--max-position", None), ("figures", "--figures", None))
"""The options of trajectory data sets that a scene set refuses: (attribute, option, its default)."""


def run_scenes(args) -> int:
    """``immnet evaluate`` on a scene set: the multi-target tracker with each filter of ``--methods``, each filter
    told the association, and the raw plots, scored by GOSPA and the identity metrics (``immnet.evaluation.scenes``)."""
    from immnet.data.scenes import load_index, load_scene
    from immnet.evaluation import scenes as sc
    from immnet.filters.multi import DEFAULT_FILTER, MultiTargetTracker, TrackFilter

    for attr, option, default in SCENE_REFUSED:
        if getattr(args, attr) != default:
            raise ValueError(f"{option} is for trajectory data sets; {args.data} is a scene set, scored by GOSPA "
                             f"(docs/evaluation.md, \"Scenes\")")
    _check_outputs(args)
    index = load_index(args.data)
    entries = [e for e in index["scenes"] if args.split == "all" or e["split"] == args.split]
    if not entries:
        raise ValueError(f"{args.data} has no {args.split} scenes (split {args.split}); --split all takes every scene")
    entries = _first(entries, args.limit)
    names = _method_names(args.methods) or [DEFAULT_FILTER]
    settings = {"associator": args.associator or "gnn"}
    for name in names:  # refused before any scene runs: a name that is not a multi-target filter (or not for JPDA)
        tracker = MultiTargetTracker(TrackFilter.by_name(name), associator=settings["associator"])
    record = sc.recorded(tracker)  # its settings but those each scene gives (the same with every filter)
    scenes = [load_scene(Path(args.data) / e["file"]) for e in entries]
    note = lambda msg: print(msg, file=sys.stderr)  # noqa: E731
    note(f"evaluating the multi-target tracker with {', '.join(names)} ({settings['associator']}) on {len(scenes)} "
         f"scenes ({args.data}, split {args.split})")
    results = sc.evaluate_scenes(scenes, names, settings=settings, note=None if args.quiet else note)
    over = {n: r["mean"]["over_interval"] for n, r in results.items() if r["mean"]["over_interval"]}
    for n, k in over.items():
        note(f"note: {n}: {k} scans took longer than the interval to the next scan")
    print(sc.format_table(results))
    _write_text(args.markdown, sc.format_table(results, markdown=True), note)
    doc = {"data": str(args.data), "split": args.split, "kind": "scenes", "scenes": [s.name for s in scenes],
           "gospa": {"c": 200.0, "p": 2.0, "alpha": 2.0}, "tracker": record, "methods": results}
    _write_json(args.json, doc, note)
    if wandb_log.wanted(args.wandb):
        config = {"command": "evaluate", "data": {"path": str(args.data), "split": args.split, "kind": "scenes",
                                                  "scenes": doc["scenes"], "limit": args.limit,
                                                  "spec": scenes[0].meta.get("spec")},
                  "methods": {n: filter_info(n) for n in names}, "tracker": record, "gospa": doc["gospa"]}
        run = wandb_log.start(config, args.wandb_project, args.wandb_group, args.wandb_name, args.wandb_dir)
        wandb_log.log_scenes(run, results)
        _finish(run, note)
    return 0


def filter_info(name: str) -> dict:
    """A multi-target filter in a W&B run's config: a shipped network's name and checkpoint
    (``wandb_log.checkpoint_info``), a method's config (``wandb_log.method_info``), or the bands of the IMMs by scan
    interval and each one's config (``immnet.filters.registry.MULTI_TARGET_BANDS``)."""
    from immnet.checkpoints import SHIPPED, shipped
    from immnet.filters.registry import MULTI_TARGET_BANDS, MULTI_TARGET_FILTER

    if name in SHIPPED:
        return {"network": name, "checkpoint": wandb_log.checkpoint_info(shipped(name))}
    if name == MULTI_TARGET_FILTER:
        return {"by_interval": [{"longest_interval": longest, "method": m, **wandb_log.method_info(m)}
                                for longest, m in MULTI_TARGET_BANDS]}
    return wandb_log.method_info(name)


def _check_outputs(args) -> None:
    """The error that writing ``--json``, ``--markdown`` or ``--figures`` would meet (a read-only folder, a path
    under a file), raised before the scoring rather than after it."""
    from immnet.data.scratch import check_writable

    for path in (args.json, args.markdown):
        if path is not None:
            check_writable(path)
    if args.figures is not None:
        check_writable(args.figures, "into")


def _write_text(path: Path | None, text: str, note) -> None:
    """``text`` and a newline written to ``path`` whole or not at all (through a temporary sibling), its folder made,
    and noted; nothing where ``path`` is None (the option not given)."""
    from immnet.data.scratch import publishing

    if path is None:
        return
    with publishing(path) as tmp:
        tmp.write_text(text + "\n")
    note(f"wrote {path}")


def _write_json(path: Path | None, doc: dict, note) -> None:
    """``doc`` as JSON (every non-finite number ``null``) by :func:`_write_text`; nothing where ``path`` is None."""
    from immnet.evaluation.runner import finite_or_none

    if path is not None:
        _write_text(path, json.dumps(finite_or_none(doc), indent=2, allow_nan=False), note)


def _finish(run, note) -> None:
    """Close the W&B ``run``; where it is offline, note how to upload it."""
    where = wandb_log.finish(run)
    if where:
        note(f"W&B run {run.id} (offline): {where}; upload with `wandb sync {where}`")


def log_run(args, results, rows, figures, data, meta, split, note) -> None:
    """The evaluation as a W&B run (``immnet.evaluation.wandb_log``): config, table, scalars, curves, figures."""
    from immnet.data.times import nominal_dt
    from immnet.evaluation.metrics import avg_curve

    ckpt = _checkpoints(args.checkpoint, _candidates(args.methods))  # select_methods' mapping (a skipped one's too)
    config = {"command": "evaluate",
              "data": {"path": str(args.data), "split": split, "n_trajectories": data.batch_size[0], "limit": args.limit,
                       "meta": meta},
              "methods": {n: wandb_log.method_info(n, ckpt.get(n)) for n in results},
              "guard": args.guard, "told_r": args.told_r, "sigma_q": args.sigma_q, "max_position": args.max_position,
              "seed": args.seed}
    run = wandb_log.start(config, args.wandb_project, args.wandb_group, args.wandb_name, args.wandb_dir)
    curves = {n: avg_curve(r["rmse_over_time"]) for n, r in results.items()}
    wandb_log.log_results(run, rows, curves, figures, dt=float(nominal_dt(data[:1])[0]))  # x: scan k at k dt
    _finish(run, note)


def run_tune(args) -> int:
    from immnet.config import checkout

    if args.n < 1:
        raise ValueError("--n must be positive")
    if not Path(args.data).is_dir():
        raise ValueError(f"tune-imm needs a generated data directory (it tunes on its validation split): {args.data}")
    from immnet.evaluation.tuning import tune_imm

    data, _ = load_split(args.data, args.split, args.n)
    out = args.out or (checkout() or Path(".")) / "configs" / "methods" / "imm-tuned.yaml"
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    print(f"tuning IMM on {data.batch_size[0]} validation trajectories of {args.data}", file=sys.stderr)
    best = tune_imm(data, out, progress=True)
    from immnet.evaluation.runner import finite_or_none

    print(json.dumps(finite_or_none(best), indent=2, default=str, allow_nan=False))
    print(f"wrote {out}", file=sys.stderr)
    return 0
