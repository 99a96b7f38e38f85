"""Produce the shipped weights: write stage 2's training data, train recipes/pretrained.yaml, export
the last stage's checkpoint into immnet/pretrained/immnet.ckpt, score it on a fresh test set beside the
baselines, and write immnet/pretrained/provenance.json and PROVENANCE.md.

Run (needs the quick data: `bash scripts/main.sh` makes it):
    .venv/bin/python scripts/make_pretrained.py [--skip-training [--commit C] [--wandb-runs ID,...] [--note TEXT]]

The training's W&B runs (group "pretrained", one per stage; docs/wandb.md) are recorded by id in the
provenance (`wandb`), found as the run directories the training added under runs/wandb; with
--skip-training, --wandb-runs names them (none named: none recorded).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "runs/pretrained"
OUT = ROOT / "immnet/pretrained"
TEST_SEED, TEST_N = 77, 1000
TRAIN_SEED, TRAIN_N = 41, 12000  # stage 2's data, written where recipes/pretrained-stage2.yaml reads it
STAGE2_DATA = yaml.safe_load((ROOT / "recipes/pretrained-stage2.yaml").read_text())["data"]["data"]


def last_checkpoint(chain: Path) -> Path:
    """Where the last stage of a chained recipe writes its best checkpoint (its ModelCheckpoint's dirpath/filename)."""
    from immnet.training.cli import stage_entry

    stages = yaml.safe_load(chain.read_text())["stages"]
    configs, _ = stage_entry(stages[-1], len(stages) - 1)
    for config in reversed(configs):  # the last config that names the callbacks wins
        if isinstance(config, str):
            config = yaml.safe_load((ROOT / config).read_text())
        for cb in (config.get("trainer") or {}).get("callbacks") or []:
            if cb.get("class_path", "").endswith("ModelCheckpoint"):
                args = cb["init_args"]
                return ROOT / args["dirpath"] / f"{args.get('filename', 'best')}.ckpt"
    raise ValueError(f"{chain}: its last stage has no ModelCheckpoint callback to export from")


WANDB_DIR = ROOT / "runs/wandb"  # where the training's logger (immnet fit's default) writes its runs
WANDB_GROUP = "pretrained"  # unless WANDB_RUN_GROUP names another


def wandb_runs() -> set[str]:
    """The ids of the W&B runs under runs/wandb (directories ``[offline-]run-<time>-<id>``)."""
    return {p.name.rsplit("-", 1)[-1] for p in WANDB_DIR.glob("*run-*") if p.is_dir()}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--skip-training", action="store_true")
    p.add_argument("--commit", default="", help="with --skip-training: the commit the weights were trained at (default: HEAD)")
    p.add_argument("--wandb-runs", default="", help="with --skip-training: the W&B run ids of the training, comma-separated")
    p.add_argument("--note", default="", help="how this training run departed from the recipe, if it did (kept in the provenance)")
    a = p.parse_args()
    # the commit the weights were trained at (read before training: later commits may land meanwhile)
    group = os.environ.get("WANDB_RUN_GROUP") or WANDB_GROUP  # the W&B group of the training's runs
    rev = a.commit if a.skip_training and a.commit else "HEAD"
    commit = subprocess.run(["git", "rev-parse", "--verify", f"{rev}^{{commit}}"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    if not commit:
        p.error(f"--commit {a.commit!r} is not a commit of this repository")
    from immnet.data.storage import load_dataset, write_dataset

    train_dir = ROOT / STAGE2_DATA
    if not a.skip_training:
        if not (train_dir / "meta.json").exists():
            write_dataset(train_dir, n=TRAIN_N, seed=TRAIN_SEED, overwrite=True, workers=2, progress=True)
        before = wandb_runs()
        env = {**os.environ, "WANDB_RUN_GROUP": group, "WANDB_JOB_TYPE": "train"}  # runs "pretrained 1/4" ... (run_stages)
        subprocess.run([sys.executable, "-m", "immnet.cli", "fit", "--config", "recipes/pretrained.yaml"], cwd=ROOT,
                       check=True, env=env)
        run_ids = sorted(wandb_runs() - before)
    else:
        run_ids = [r.strip() for r in a.wandb_runs.split(",") if r.strip()]
    from immnet.filters.methods import ORDER, build_method
    from immnet.evaluation.runner import evaluate, to_json
    from immnet.evaluation.table import format_markdown, format_table
    from immnet.training.export import export_weights

    ckpt = last_checkpoint(ROOT / "recipes/pretrained.yaml")
    export_weights(ckpt, OUT / "immnet.ckpt")
    from immnet.checkpoints import record_shipped

    record_shipped("3dlast")  # the weights table names the new file's weights
    test_dir = RUN / "test"
    if not (test_dir / "meta.json").exists():
        write_dataset(test_dir, n=TEST_N, seed=TEST_SEED, overwrite=True)
    data, _ = load_dataset(test_dir)
    names = tuple(n for n in ORDER if n != "kalmannet")  # every method of the results table but the plain KalmanNet
    methods = {n: build_method(n, OUT / "immnet.ckpt" if n == "immnet" else None) for n in names}
    rows = to_json(evaluate(methods, data, progress=True))
    print(format_table(rows))
    avg = {n: r["rmse"]["avg"] for n, r in rows.items()}
    from immnet.checkpoints import CHECKSUM_KEY, load_checkpoint
    from immnet.tracking import Tracker

    net = Tracker.pretrained("3dlast").net  # the file just written (the default is the bank of the shipped networks)
    prov = {
        "file": "immnet/pretrained/immnet.ckpt",
        "weights_sha256": load_checkpoint(OUT / "immnet.ckpt")[CHECKSUM_KEY],
        "recipe": "recipes/pretrained.yaml",
        "made_by": ".venv/bin/python scripts/make_pretrained.py",
        "date": datetime.date.today().isoformat(),
        "commit": commit,
        "model_set": net.model_set.names,
        "guard": None if net.interact.guard is None else net.interact.guard.to_config(),
        "data": {"stage1": "runs/quick/data/train: 3000 trajectories, seed 11 (val: 5 % of it)",
                 "stage1_single_mode": "4 x 600 trajectories, seeds 12 (cv), 13 (ca), 14 (ct+), 15 (ct-)",
                 "stage2": f"{STAGE2_DATA}: {TRAIN_N} trajectories, seed {TRAIN_SEED} (val: 5 % of it)",
                 "stage3": "the same as stage 2", "stage4": "the same as stage 2"},
        "note": a.note,
        "wandb": {"project": "immnet", "group": group if not a.skip_training else None, "runs": run_ids} if run_ids else None,
        "test": {"n": TEST_N, "seed": TEST_SEED, "note": "fresh 3D-LAST, never seen in training or tuning"},
        "metrics": {n: r["rmse"] for n, r in rows.items()},
        "mode_accuracy": rows["immnet"].get("mode_accuracy"),
        "claims": {
            # what the test in tests/test_pretrained.py holds the file to, rounded up to 0.01
            "ratio_to_clairvoyant": math.ceil(100 * avg["immnet"] / avg["clairvoyant"]) / 100,
            "ratio_to_imm_tuned": math.ceil(100 * avg["immnet"] / avg["imm-tuned"]) / 100,
        },
    }
    (OUT / "provenance.json").write_text(json.dumps(prov, indent=2, allow_nan=False) + "\n")
    (OUT / "PROVENANCE.md").write_text(
        "# Shipped IMMNet weights\n\n"
        f"`immnet.ckpt` ({(OUT / 'immnet.ckpt').stat().st_size / 2**20:.1f} MB): IMMNet with experts "
        f"{', '.join(prov['model_set'])}, trained by `{prov['recipe']}` at commit `{commit[:10]}` "
        f"({prov['date']}) and exported by `{prov['made_by']}`.\n\n"
        f"The file carries the SHA-256 of its weights (`weights_sha256`: {prov['weights_sha256']}, over the state_dict's "
        "names, dtypes, shapes and bytes); every load checks it and refuses the file if the weights disagree "
        "(`immnet.checkpoints`, docs/checkpoints.md).\n\n"
        + (
            "It carries a range guard (`immnet/imm/guard.py`: 3D-LAST's surveillance region, where a target turns "
            f"back beyond {prov['guard']['outer']:.0f} m and within {prov['guard']['inner']:.0f} m of the radar"
            + (f", and its speed bounds, {prov['guard']['speed_min']:.0f}-{prov['guard']['speed_max']:.0f} m/s, where a "
               "CA maneuver turns for one scan" if prov["guard"].get("speeds") else "")
            + "). For radar "
            "data from another region load it with `Tracker.pretrained(\"3dlast\", guard=None)` or a region of your own, or run "
            "`immnet track --weights 3dlast --guard none` (or `--guard OUTER,INNER`).\n\n"
            if prov["guard"] else ""
        )
        + (f"Departure from the recipe: {a.note}\n\n" if a.note else "")
        + (f"W&B: the training's runs {', '.join(f'`{r}`' for r in run_ids)} (project `immnet`"
           + (f", group `{group}`" if not a.skip_training else "") + "; docs/wandb.md).\n\n"
           if run_ids else "W&B: no run id recorded for this training (`wandb: null` in provenance.json).\n\n")
        + f"Training data: stage 1 {prov['data']['stage1']}, with the single-mode data {prov['data']['stage1_single_mode']}; "
        f"stages 2 to 4 {prov['data']['stage2']}.\n\n"
        f"Test set: {TEST_N} fresh trajectories (seed {TEST_SEED}). RMSE of position in metres:\n\n"
        + format_markdown(rows)
        + f"\n\nClaims checked by `tests/test_pretrained.py` on freshly generated data: Average RMSE at most "
        f"{prov['claims']['ratio_to_clairvoyant']}x the clairvoyant bound and at most "
        f"{prov['claims']['ratio_to_imm_tuned']}x IMM-Tuned.\n"
    )
    print(f"wrote {OUT / 'provenance.json'} and PROVENANCE.md", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
