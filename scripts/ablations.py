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
    args = [sys.executable, "-m", "immnet.cli", "fit", "--config", base, "--config", f"configs/ablations/{name}.yaml"]
    if from_stage1:
        args += ["--model.init_args.stage1_checkpoint", str(QUICK / "stage1/checkpoints/best.ckpt")]
    print(f"[ablations] training {name}", file=sys.stderr, flush=True)
    subprocess.run(args, cwd=ROOT, check=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--skip-training", action="store_true", help="only evaluate existing checkpoints")
    p.add_argument("--only", nargs="*", default=None, help="train only these ablations")
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
    methods = {
        "immnet (full)": IMMNetMethod(QUICK / "stage2/checkpoints/best.ckpt", name="immnet (full)"),
        "range guard removed (Markov transitions alone)": IMMNetMethod(ckpt("no-guard")),
        "classifier -> uniform mix": IMMNetMethod(ckpt("uniform-mix")),
        "classifier -> IMM Bayesian update alone": IMMNetMethod(ckpt("bayes-mode")),
        "classifier -> Transformer alone (the paper's)": IMMNetMethod(ckpt("transformer-mode")),
        "IMM interaction -> fused input (SPEC's predict)": IMMNetMethod(ckpt("fused-input")),
        "KalmanNet -> analytic gain (fixed noise)": IMMNetMethod(ckpt("analytic-gain")),
        "single expert (plain KalmanNet, CA)": KalmanNetMethod(ckpt("single-expert"), expert="ca"),
        "adaptive -> fixed +/-5 deg/s turn experts": IMMNetMethod(ckpt("fixed-turn-rate")),
        "the paper's experts and classifier (KalmanNet gain, Transformer)": IMMNetMethod(ckpt("kalmannet-experts")),
        "imm-ekf": build_method("imm-ekf"),
        "imm-ekf-guard": build_method("imm-ekf-guard"),
        "clairvoyant": build_method("clairvoyant"),
    }
    rows = to_json(evaluate(methods, data, progress=True))
    print(format_table(rows))
    out = ROOT / "runs/ablations/results.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(format_markdown(rows) + "\n")
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
