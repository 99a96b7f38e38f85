"""Train the ablations of configs/ablations with the quick recipe's budgets, then score them beside
the full quick IMMNet on the quick test set in one run; writes runs/ablations/results.md. Each ablation's
file says everything: what it runs (a chain of stages), its row's label and its weights.

Run (after `bash scripts/main.sh`, which makes the data, the quick run and the single-expert
ablation, the main table's plain KalmanNet, which is not trained again here):
    .venv/bin/python scripts/ablations.py [--skip-training]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
QUICK = ROOT / "runs/quick"
ABLATIONS = ROOT / "configs/ablations"
MADE_BY_MAIN = {"single-expert"}  # scripts/main.sh trains it (the main table's plain KalmanNet)


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


def train(name: str) -> None:
    args = [sys.executable, "-m", "immnet.cli", "fit", "--config", str(ABLATIONS / f"{name}.yaml"),
            "--overwrite_checkpoints", "true"]  # retrain: replace an earlier run's checkpoints
    print(f"[ablations] training {name}", file=sys.stderr, flush=True)
    subprocess.run(args, cwd=ROOT, check=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--skip-training", action="store_true", help="only evaluate existing checkpoints")
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
    from immnet.evaluation.methods import build_method
    from immnet.tracking import IMMNetMethod, KalmanNetMethod

    data, _ = load_dataset(QUICK / "data/test")
    methods = {"immnet (full)": IMMNetMethod(QUICK / "stage2/checkpoints/best.ckpt", name="immnet (full)")}
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
    rows = to_json(evaluate(methods, data, progress=True))
    print(format_table(rows))
    out = ROOT / "runs/ablations/results.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(format_markdown(rows) + "\n")
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
