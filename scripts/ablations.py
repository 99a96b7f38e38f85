"""Train the ablations of configs/ablations with the quick recipe's budgets, then score them beside
the full quick IMMNet on the quick test set in one run; writes runs/ablations/results.md. Each ablation's
file says everything: what it runs (a chain of stages), its row's label and its weights.

Run (after `bash scripts/main.sh`, which makes the data, the quick run and the single-expert
ablation, the main table's plain KalmanNet, which is not trained again here):
    .venv/bin/python scripts/ablations.py [--skip-training] [--no-wandb]

W&B (docs/wandb.md; offline unless WANDB_MODE=online): every run in the group "ablations": each
ablation's training stages, then one evaluation run per ablation and one for the full model (config:
the ablation's file, its label and the parts it swaps; summary: its own row's numbers, `rmse_avg` ...,
and `ratio_to_full`), and the run "table" holding the whole table and the RMSE-over-time curves.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
QUICK = ROOT / "runs/quick"
ABLATIONS = ROOT / "configs/ablations"
MADE_BY_MAIN = {"single-expert"}
GROUP = "ablations"  # the W&B group of every run of this script (WANDB_RUN_GROUP overrides it)
FULL = "immnet (full)"
OWN = ("rmse_x", "rmse_y", "rmse_z", "rmse_avg", "post_switch_avg", "mode_accuracy", "ratio_to_bound")
"""The summary keys of an ablation's run: its own row of the results table (``wandb_log.table_rows``)."""  # scripts/main.sh trains it (the main table's plain KalmanNet)


def ablations() -> dict:
    """Every ``configs/ablations/NAME.yaml``: its row ``label``, its weights ``checkpoint`` and how it is
    scored (``evaluate``: IMMNet unless it says ``method: kalmannet``), from the file itself."""
    out = {}
    for path in sorted(ABLATIONS.glob("*.yaml")):
        spec = yaml.safe_load(path.read_text())
        missing = [k for k in ("label", "checkpoint", "stages") if k not in spec]
        if missing:
            raise SystemExit(f"{path}: an ablation names its {', '.join(missing)}")
        out[path.stem] = spec
    return out


def swapped_parts(spec: dict) -> dict[str, str]:
    """What an ablation changes, from its file: every setting of its stages' inline configs under
    ``model`` and ``data`` (``init_args`` levels dropped: ``model.net.guard``; a class by its
    ``class_path``, then its arguments), except the checkpoints a stage starts from:
    ``{"model.net.guard": "False", "model.net.p_stay": "0.995"}``."""
    from immnet.training.cli import stage_entry

    out: dict[str, str] = {}

    def walk(prefix: str, value) -> None:
        if isinstance(value, dict) and value:
            if "class_path" in value:  # a swapped class: its name, then its arguments
                out[prefix] = value["class_path"]
            for k, v in value.items():
                if k != "class_path":
                    walk(prefix if k == "init_args" else f"{prefix}.{k}", v)
        elif not prefix.endswith(("stage1_checkpoint", "init_checkpoint")):
            out[prefix] = str(value)

    for i, stage in enumerate(spec["stages"]):
        configs, _ = stage_entry(stage, i)
        for config in configs:
            if isinstance(config, dict):
                for part in ("model", "data"):
                    if part in config:
                        walk(part, config[part])
    return out


def train(name: str) -> None:
    args = [sys.executable, "-m", "immnet.cli", "fit", "--config", str(ABLATIONS / f"{name}.yaml"),
            "--overwrite_checkpoints", "true"]  # retrain: replace an earlier run's checkpoints
    print(f"[ablations] training {name}", file=sys.stderr, flush=True)
    env = {**os.environ, "WANDB_RUN_GROUP": os.environ.get("WANDB_RUN_GROUP", GROUP), "WANDB_JOB_TYPE": "train"}
    subprocess.run(args, cwd=ROOT, check=True, env=env)


def log_wandb(results: dict, rows: dict, table: dict, chosen: list[str]) -> None:
    """The W&B runs of the evaluation (module docstring): one per ablation and the full model, and "table"."""
    from immnet.evaluation import wandb_log
    from immnet.evaluation.metrics import avg_curve

    group = os.environ.get("WANDB_RUN_GROUP", GROUP)
    full = FULL
    refs = [n for n in rows if n != full and n not in {table[a]["label"] for a in chosen}]
    curves = {n: avg_curve(r["rmse_over_time"]) for n, r in results.items()}
    data = {"path": str(QUICK / "data/test"), "split": "all", "n_trajectories": next(iter(results.values()))["counts"]["trajectories"]}
    numbers = {row[0]: row for row in wandb_log.table_rows(rows)}  # the results table's numbers, by method
    where = []

    def one(run_name: str, label: str, config: dict, job_type: str, shown: list[str]) -> None:
        run = wandb_log.start({**config, "data": data}, group=group, name=run_name, job_type=job_type,
                              directory=ROOT / "runs")
        own = dict(zip(OWN, numbers[label][1:8])) if label else {}
        if own.get("rmse_avg") is not None and numbers[full][4] is not None:
            own["ratio_to_full"] = own["rmse_avg"] / numbers[full][4]
        wandb_log.log_results(run, {n: rows[n] for n in shown}, {n: curves[n] for n in shown},
                              summary={k: v for k, v in own.items() if v is not None})
        where.append(wandb_log.finish(run))

    full_ckpt = QUICK / "stage2/checkpoints/best.ckpt"
    one("full", full, {"ablation": "none", "label": full, "swaps": {},
                       "checkpoint": wandb_log.checkpoint_info(full_ckpt)}, "ablation", [full, *refs])
    for name in chosen:
        spec = table[name]
        one(name, spec["label"], {"ablation": name, "label": spec["label"], "file": f"configs/ablations/{name}.yaml",
                                  "swaps": swapped_parts(spec), "checkpoint": wandb_log.checkpoint_info(ROOT / spec["checkpoint"])},
            "ablation", [full, spec["label"], *refs])
    one("table", "", {"ablations": {n: {"label": table[n]["label"], "swaps": swapped_parts(table[n])} for n in chosen}},
        "ablations-table", list(rows))
    where = [w for w in where if w]
    if where:
        print(f"[ablations] W&B offline runs (group {group}); upload with:\n  wandb sync {' '.join(where)}", file=sys.stderr)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--skip-training", action="store_true", help="only evaluate existing checkpoints")
    p.add_argument("--wandb", action=argparse.BooleanOptionalAction, default=True,
                   help="log the evaluation as W&B runs of the group 'ablations' (default; offline unless WANDB_MODE=online)")
    p.add_argument("--only", nargs="*", default=None, help="train and score only these ablations (beside the full model and the references)")
    a = p.parse_args()
    table = ablations()
    unknown = set(a.only or ()) - set(table)
    if unknown:
        raise SystemExit(f"unknown ablation(s) {sorted(unknown)}; known: {sorted(table)}")
    chosen = a.only or list(table)
    if not a.skip_training:
        for name in chosen:
            done = ROOT / table[name]["checkpoint"]
            if a.only is None and name in MADE_BY_MAIN and done.is_file():
                print(f"[ablations] {name}: using {done} from scripts/main.sh", file=sys.stderr)
                continue
            train(name)
    from immnet.data.storage import load_dataset
    from immnet.evaluation.runner import evaluate, to_json
    from immnet.evaluation.table import format_markdown, format_table
    from immnet.filters.methods import build_method
    from immnet.tracking import IMMNetMethod, KalmanNetMethod

    data, _ = load_dataset(QUICK / "data/test")
    methods = {FULL: IMMNetMethod(QUICK / "stage2/checkpoints/best.ckpt", name=FULL)}
    for name in chosen:
        spec = table[name]
        how = spec.get("evaluate") or {}
        ckpt = ROOT / spec["checkpoint"]
        if how.get("method") == "kalmannet":
            methods[spec["label"]] = KalmanNetMethod(ckpt, expert=how.get("expert"))
        else:
            methods[spec["label"]] = IMMNetMethod(ckpt)
    methods |= {"imm-ekf": build_method("imm-ekf"), "imm-ekf-guard": build_method("imm-ekf-guard"), "imm-ekf-guard-sticky": build_method("imm-ekf-guard-sticky"),
                "clairvoyant": build_method("clairvoyant")}
    results = evaluate(methods, data, progress=True)
    rows = to_json(results)
    print(format_table(rows))
    out = ROOT / "runs/ablations/results.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(format_markdown(rows) + "\n")
    print(f"wrote {out}", file=sys.stderr)
    from immnet.evaluation.wandb_log import wanted

    if wanted(a.wandb):  # --no-wandb, or WANDB_MODE=disabled: no run
        log_wandb(results, rows, table, chosen)
    return 0


if __name__ == "__main__":
    sys.exit(main())
