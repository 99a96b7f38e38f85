"""An evaluation's results as a W&B run (``immnet evaluate --wandb``, ``scripts/ablations.py``).

One run holds what a reader of a W&B project compares runs by (docs/wandb.md):

- its config: the data (path, split, trajectories, the data set's ``meta.json``), the methods (each
  one's config file) and the checkpoints (path, weights checksum, the shipped weights' provenance);
- ``results``: a ``wandb.Table``, one row per method (per-axis RMSE, Average, post-switch, mode
  accuracy, ratio to the clairvoyant bound; ``None`` where the results table shows "-");
- per-method scalars in the run's summary (``<method>/rmse_avg`` ...), the columns of W&B's runs table;
- ``rmse_over_time``: ``wandb.plot.line_series`` of every method's RMSE-over-time curve;
- ``confusion/<method>``: W&B's confusion-matrix chart over the counts of each method that has them;
- ``figures/<name>``: each PNG of the evaluation's figures as a ``wandb.Image``.

wandb is imported only here and only when a run starts, so that nothing changes without ``--wandb``.
A run is offline unless ``WANDB_MODE`` says otherwise (``online``, or ``disabled``: no run, no files);
group, name and job type come from the arguments, else from wandb's own environment variables
(``WANDB_RUN_GROUP``, ``WANDB_NAME``, ``WANDB_JOB_TYPE``).
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Mapping

from immnet.evaluation.table import finite, table_rows
from immnet.labels import MODE_LABELS

PROJECT = "immnet"
COLUMNS = ["method", "x [m]", "y [m]", "z [m]", "Average [m]", "post-switch [m]", "mode accuracy", "ratio to bound",
           "diverged tracks"]
"""The ``results`` table's columns (the results table's, as numbers; ``diverged tracks`` 0 for a finite method)."""


def add_arguments(parser) -> None:
    """``--wandb`` / ``--no-wandb`` and the run's project, group, name and directory."""
    g = parser.add_argument_group("W&B (docs/wandb.md)")
    g.add_argument("--wandb", action=argparse.BooleanOptionalAction, default=False,
                   help="log the results, the figures and the config as a W&B run (offline unless "
                        "WANDB_MODE=online; WANDB_MODE=disabled writes nothing)")
    g.add_argument("--wandb-project", default=None, help=f"W&B project (default: WANDB_PROJECT, else {PROJECT})")
    g.add_argument("--wandb-group", default=None, help="W&B group (default: WANDB_RUN_GROUP, else none)")
    g.add_argument("--wandb-name", default=None, help="W&B run name (default: WANDB_NAME, else W&B's own)")
    g.add_argument("--wandb-dir", type=Path, default=None,
                   help="directory the run's files go under, in DIR/wandb (default: WANDB_DIR, else the "
                        "working directory)")


def mode() -> str:
    """The run mode: ``WANDB_MODE`` if set (``online``, ``offline``, ``disabled``), else ``offline``."""
    return os.environ.get("WANDB_MODE") or "offline"


def wanted(flag: bool) -> bool:
    """Whether to log a run: ``flag`` (``--wandb``) and W&B not turned off (``WANDB_MODE=disabled``: then
    nothing of W&B runs, wandb is not imported, and the command does exactly what it does without ``--wandb``)."""
    return bool(flag) and mode() != "disabled"


def start(config: dict, project: str | None = None, group: str | None = None, name: str | None = None,
          directory: str | Path | None = None, job_type: str | None = None):
    """A new W&B run (``wandb.init``; offline unless ``WANDB_MODE`` says otherwise) holding ``config``.

    ``None`` leaves a setting to wandb's own environment variables (``WANDB_PROJECT``,
    ``WANDB_RUN_GROUP``, ``WANDB_NAME``, ``WANDB_JOB_TYPE``, ``WANDB_DIR``), else to its default here:
    project ``immnet``, job type ``evaluate``."""
    import wandb

    if directory is not None:
        Path(directory).mkdir(parents=True, exist_ok=True)
    kw = {"project": project or os.environ.get("WANDB_PROJECT") or PROJECT, "group": group, "name": name,
          "dir": None if directory is None else str(directory), "job_type": job_type or os.environ.get("WANDB_JOB_TYPE") or "evaluate"}
    return wandb.init(config=config, mode=mode(), reinit="create_new",
                      **{k: v for k, v in kw.items() if v is not None})


def scalars(rows: Mapping[str, dict]) -> dict[str, float]:
    """Per-method scalars for the run's summary: ``<method>/rmse_<axis>``, ``<method>/post_switch_avg``,
    ``<method>/mode_accuracy``, ``<method>/ratio_to_bound``, where the method has them."""
    names = ("rmse_x", "rmse_y", "rmse_z", "rmse_avg", "post_switch_avg", "mode_accuracy", "ratio_to_bound")
    return {f"{row[0]}/{k}": v for row in table_rows(rows) for k, v in zip(names, row[1:8]) if v is not None}


def log_results(run, rows: Mapping[str, dict], curves: Mapping[str, object] | None = None, figures=(), dt: float = 1.0,
                summary: Mapping[str, float] | None = None) -> None:
    """Log an evaluation into ``run``: the ``results`` table, the scalars (plus ``summary``), the
    RMSE-over-time line plot of ``curves`` (``{method: [T] curve}``, a gap as NaN), the confusion
    matrices of ``rows`` and the PNG ``figures`` (paths)."""
    import wandb

    logged = {"results": wandb.Table(columns=COLUMNS, data=table_rows(rows))}
    if curves:
        names = list(curves)
        values = [[finite(float(v)) for v in curves[n]] for n in names]
        t = [k * dt for k in range(max(len(v) for v in values))]
        logged["rmse_over_time"] = wandb.plot.line_series(xs=t, ys=values, keys=names, xname="t [s]",
                                                          title="Position RMSE over time [m]")
    for method, r in rows.items():
        if r.get("confusion") is not None:
            logged[f"confusion/{method}"] = confusion_chart(r["confusion"], f"{method}: mode confusion")
    for path in figures:
        logged[f"figures/{Path(path).stem}"] = wandb.Image(str(path))
    run.log(logged)
    run.summary.update({**scalars(rows), **(summary or {})})


def log_scenes(run, results: Mapping[str, dict]) -> None:
    """Log a scene set's evaluation (``immnet.evaluation.scenes.evaluate_scenes``) into ``run``: the ``results``
    table (``scenes.COLUMNS``, one row per method), per-method scalars ``<method>/<metric>`` (``scenes.SCALARS``,
    ``ms_per_scan_median``, ``ms_per_scan_max``) in the summary, and per method ``gospa_over_time/<method>``, a
    ``wandb.plot.line_series`` with a line per scene: GOSPA (m) at each scan against the time from the scene's first
    scan (s)."""
    import wandb

    from immnet.evaluation.scenes import COLUMNS as SCENE_COLUMNS
    from immnet.evaluation.scenes import SCALARS
    from immnet.evaluation.scenes import table_rows as scene_rows

    logged = {"results": wandb.Table(columns=SCENE_COLUMNS, data=[[row[0], *map(finite, row[1:])]
                                                                  for row in scene_rows(results)])}
    summary = {}
    for method, r in results.items():
        per = r["scenes"]
        logged[f"gospa_over_time/{method}"] = wandb.plot.line_series(
            xs=[s["t"] for s in per.values()], ys=[[finite(g) for g in s["gospa_per_scan"]] for s in per.values()],
            keys=list(per), xname="t [s]", title=f"{method}: GOSPA per scan [m]")
        m = r["mean"]
        summary |= {f"{method}/{k}": m[k] for k in SCALARS}
        summary |= {f"{method}/ms_per_scan_{k}": m["ms_per_scan"][k] for k in ("median", "max")}
    run.log(logged)
    run.summary.update(summary)


def confusion_chart(counts, title: str):
    """W&B's confusion-matrix chart (``wandb/confusion_matrix/v1``, the chart ``wandb.plot.confusion_matrix``
    draws) over counts ``C[true][predicted]``: the evaluation has the counts, not the labels per scan."""
    import wandb

    data = [[MODE_LABELS[i], MODE_LABELS[j], int(counts[i][j])] for i in range(len(counts)) for j in range(len(counts[i]))]
    return wandb.plot_table("wandb/confusion_matrix/v1", wandb.Table(columns=["Actual", "Predicted", "nPredictions"], data=data),
                            {"Actual": "Actual", "Predicted": "Predicted", "nPredictions": "nPredictions"},
                            {"title": title})


def finish(run) -> str | None:
    """Close ``run``; the offline run's directory (what ``wandb sync`` takes), or ``None`` when not offline."""
    run.finish()
    if mode() != "offline":
        return None
    return str(Path(run.dir).parent)


# --- what the config says about checkpoints ---------------------------------------------------
def checkpoint_info(path) -> dict:
    """A checkpoint in the run's config: its path, the checksum of its weights (docs/checkpoints.md) and,
    for weights with a provenance file beside them (the shipped ones: ``immnet.checkpoints.provenance_file``),
    that provenance."""
    from immnet.checkpoints import CHECKSUM_KEY, load_checkpoint, provenance_file

    path = Path(path)
    info: dict = {"path": str(path)}
    try:
        info["weights_sha256"] = load_checkpoint(path).get(CHECKSUM_KEY)
    except Exception as err:  # noqa: BLE001 - the method that reads it reports a bad file; here it is a note
        info["error"] = str(err)
    prov = provenance_file(path)
    if prov.is_file():
        info["provenance"] = json.loads(prov.read_text())
    return info


def method_info(name: str, checkpoint=None) -> dict:
    """A method in the run's config: its config file and init_args, and its checkpoint
    (:func:`checkpoint_info`; a learned method given none runs the shipped weights)."""
    from immnet.filters.methods import BUILTIN, _method_class, method_config, takes_checkpoint

    if name in BUILTIN:
        return {"builtin": True}
    _, init_args = _method_class(name)
    info = {"config": str(method_config(name)), "init_args": {k: str(v) for k, v in init_args.items()}}
    if checkpoint is None and takes_checkpoint(name):
        from immnet.checkpoints import PRETRAINED

        checkpoint = PRETRAINED if init_args.get("checkpoint") is None else init_args["checkpoint"]
    if checkpoint is not None:
        info["checkpoint"] = checkpoint_info(checkpoint)
    return info
