"""Ship IMMNet for real flights: export recipes/real-finetune.yaml's best checkpoint into
immnet/pretrained/immnet-real.ckpt, score it on the held-out test flights of collections/quickstart beside the
model-based filters tuned on the training flights, and write immnet/pretrained/provenance-real.json and
PROVENANCE-real.md.

Run (after `bash scripts/real.sh`, which makes the data and the fine-tuned checkpoint):
    .venv/bin/python scripts/make_real_pretrained.py [--commit C] [--note TEXT]
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "runs/real"
OUT = ROOT / "immnet/pretrained"
CKPT = RUN / "finetune/checkpoints/best.ckpt"
TEST = RUN / "data/quickstart-1s/test"
METHODS = ("measurements", "imm-tuned", "imm-ekf", "real-ca", "real-imm", "real-imm-axis", "immnet", "immnet-real")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--commit", default="HEAD", help="the commit the weights were trained at (default: HEAD)")
    p.add_argument("--note", default="", help="how the training departed from the recipe, if it did")
    a = p.parse_args()
    commit = subprocess.run(["git", "rev-parse", "--verify", f"{a.commit}^{{commit}}"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    if not commit:
        p.error(f"--commit {a.commit!r} is not a commit of this repository")
    from immnet.checkpoints import CHECKSUM_KEY, load_checkpoint
    from immnet.data.storage import load_dataset
    from immnet.evaluation.methods import build_method
    from immnet.evaluation.runner import evaluate, to_json
    from immnet.evaluation.table import format_markdown, format_table
    from immnet.imm.guard import parse_guard
    from immnet.training.export import export_weights

    out = export_weights(CKPT, OUT / "immnet-real.ckpt")
    data, meta = load_dataset(TEST)
    methods = {n: build_method(n, guard=parse_guard("none")) for n in METHODS}  # immnet-real: the file just written
    rows = to_json(evaluate(methods, data, progress=True))
    print(format_table(rows))
    avg = {n: r["rmse"]["avg"] for n, r in rows.items()}
    best = min((n for n in METHODS if n.startswith(("real-", "imm-"))), key=avg.get)
    prov = {
        "file": "immnet/pretrained/immnet-real.ckpt",
        "weights_sha256": load_checkpoint(out)[CHECKSUM_KEY],
        "recipe": "recipes/real-finetune.yaml",
        "init": "immnet/pretrained/immnet.ckpt (3D-LAST)",
        "made_by": ".venv/bin/python scripts/make_real_pretrained.py",
        "date": datetime.date.today().isoformat(),
        "commit": commit,
        "data": {"train": "runs/real/data/quickstart-1s/train: collections/quickstart's training flights (immnet data "
                          "adsb --seed 0), 1 s scans, r ~ U[1, 7] m", "val": "runs/real/data/quickstart-1s/val",
                 "flights": {s: len(meta["flights"][s]) if isinstance(meta.get("flights"), dict) else None
                             for s in ("train", "val", "test")}},
        "guard": None,
        "scan_interval": 1.0,
        "note": a.note,
        "test": {"data": "runs/real/data/quickstart-1s/test", "n": data.batch_size[0],
                 "note": "quickstart's test flights: no flight of them trained or tuned on"},
        "metrics": {n: r["rmse"] for n, r in rows.items()},
        "claims": {  # what tests/test_pretrained.py holds the file to, rounded up to 0.01
            "ratio_to_best_model_based": math.ceil(100 * avg["immnet-real"] / avg[best]) / 100,
            "best_model_based": best,
            "ratio_to_immnet_3dlast": math.ceil(100 * avg["immnet-real"] / avg["immnet"]) / 100,
        },
    }
    (OUT / "provenance-real.json").write_text(json.dumps(prov, indent=2, allow_nan=False) + "\n")
    (OUT / "PROVENANCE-real.md").write_text(
        "# Shipped IMMNet weights for real flights\n\n"
        f"`immnet-real.ckpt` ({out.stat().st_size / 2**20:.1f} MB, `weights_sha256` {prov['weights_sha256']}): the 3D-LAST "
        f"weights (`immnet.ckpt`) fine-tuned by `{prov['recipe']}` on the training flights of traffic's "
        f"`collections/quickstart` seen by a simulated radar at 1 s scans, without a range guard, at commit "
        f"`{commit[:10]}` ({prov['date']}), exported by `{prov['made_by']}`. Registry name `immnet-real`; it takes "
        "1 s scans only (a fixed-interval network).\n\n"
        + (f"Departure from the recipe: {a.note}\n\n" if a.note else "")
        + f"Test set: the {data.batch_size[0]} windows of quickstart's test flights (never trained or tuned on). "
        "RMSE of position in metres (guards off):\n\n"
        + format_markdown(rows)
        + f"\n\nClaims checked by `tests/test_pretrained.py`: Average RMSE at most {prov['claims']['ratio_to_best_model_based']}x "
        f"{best} (the best model-based filter tuned on the same training flights) and at most "
        f"{prov['claims']['ratio_to_immnet_3dlast']}x the 3D-LAST weights.\n"
    )
    print(f"wrote {out}, provenance-real.json and PROVENANCE-real.md", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
