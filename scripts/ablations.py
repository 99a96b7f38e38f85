"""Train the ablations of configs/ablations with the quick recipe's budgets, then score them beside
the full quick IMMNet on the quick test set in one run; writes runs/ablations/results.md.

Run (after `bash scripts/main.sh`, which makes the data, the quick run and the single-expert
ablation, the main table's plain KalmanNet, which is not trained again here):
    .venv/bin/python scripts/ablations.py [--skip-training]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
QUICK = ROOT / "runs/quick"
ABLATIONS = {  # name: (base recipe, needs the quick stage-1 experts)
    "no-guard": ("recipes/quick-stage2.yaml", True),
    "uniform-mix": ("recipes/quick-stage2.yaml", True),
    "bayes-mode": ("recipes/quick-stage2.yaml", True),
    "transformer-mode": ("recipes/quick-stage2.yaml", True),
    "fused-input": ("recipes/quick-stage2.yaml", True),
    "analytic-gain": ("recipes/quick-stage2.yaml", False),
    "single-expert": ("recipes/quick-stage1.yaml", False),
    "fixed-turn-rate": ("recipes/quick.yaml", False),  # both stages: the experts change
    "kalmannet-experts": ("recipes/quick.yaml", False),
}
MADE_BY_MAIN = {"single-expert"}  # scripts/main.sh trains it (the main table's plain KalmanNet)


def ckpt(name: str) -> Path:
    return ROOT / "runs/ablations" / name / "checkpoints/best.ckpt"


def train(name: str) -> None:
    base, from_stage1 = ABLATIONS[name]
    args = [sys.executable, "-m", "immnet.cli", "fit", "--config", base, "--config", f"configs/ablations/{name}.yaml",
            "--overwrite_checkpoints", "true"]  # retrain: replace an earlier run's checkpoints
    if from_stage1:
        args += ["--model.init_args.stage1_checkpoint", str(QUICK / "stage1/checkpoints/best.ckpt")]
    print(f"[ablations] training {name}", file=sys.stderr, flush=True)
    subprocess.run(args, cwd=ROOT, check=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--skip-training", action="store_true", help="only evaluate existing checkpoints")
    p.add_argument("--only", nargs="*", default=None, help="train and score only these ablations (beside the full model and the references)")
    a = p.parse_args()
    if not a.skip_training:
        for name in a.only or ABLATIONS:
            if a.only is None and name in MADE_BY_MAIN and ckpt(name).is_file():
                print(f"[ablations] {name}: using {ckpt(name)} from scripts/main.sh", file=sys.stderr)
                continue
            train(name)
    from immnet.data.storage import load_dataset
    from immnet.evaluation.runner import evaluate, to_json
    from immnet.evaluation.table import format_markdown, format_table
    from immnet.evaluation.methods import build_method
    from immnet.tracking import IMMNetMethod, KalmanNetMethod

    data, _ = load_dataset(QUICK / "data/test")
    rows_of = {  # ablation: (row label, method)
        "no-guard": ("range guard removed (Markov transitions alone)", lambda: IMMNetMethod(ckpt("no-guard"))),
        "uniform-mix": ("classifier -> uniform mix", lambda: IMMNetMethod(ckpt("uniform-mix"))),
        "bayes-mode": ("classifier -> IMM Bayesian update alone", lambda: IMMNetMethod(ckpt("bayes-mode"))),
        "transformer-mode": ("classifier -> Transformer alone (the paper's)", lambda: IMMNetMethod(ckpt("transformer-mode"))),
        "fused-input": ("IMM interaction -> fused input (the paper's predict; no guard)", lambda: IMMNetMethod(ckpt("fused-input"))),
        "analytic-gain": ("KalmanNet -> analytic gain (fixed noise)", lambda: IMMNetMethod(ckpt("analytic-gain"))),
        "single-expert": ("single expert (plain KalmanNet, CA)", lambda: KalmanNetMethod(ckpt("single-expert"), expert="ca")),
        "fixed-turn-rate": ("adaptive -> fixed +/-5 deg/s turn experts", lambda: IMMNetMethod(ckpt("fixed-turn-rate"))),
        "kalmannet-experts": ("the paper's experts and classifier (KalmanNet gain, Transformer; no guard)",
                              lambda: IMMNetMethod(ckpt("kalmannet-experts"))),
    }
    unknown = set(a.only or ()) - set(rows_of)
    if unknown:
        raise SystemExit(f"unknown ablation(s) {sorted(unknown)}; known: {sorted(rows_of)}")
    methods = {"immnet (full)": IMMNetMethod(QUICK / "stage2/checkpoints/best.ckpt", name="immnet (full)")}
    for name in a.only or rows_of:
        label, make = rows_of[name]
        methods[label] = make()
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
