"""How the bank of networks weighs its members, compared on validation sets: the filters' likelihood or the reported
track's, untempered or to the power 0.5 (docs/tracking.md "A bank of networks", where the shipped one was chosen).

    python scripts/bank_weighing.py --data runs/real/data/quickstart-1s/val --data runs/real/data/quickstart-5s/val \\
        --data runs/general/data/dev-1s --data runs/general/data/dev-4.5-5.5s [--json weighing.json]

Each cell one run of the shipped bank's members (``NetworkBank.from_names``) with that weighing, the table's Average
RMSE (``immnet evaluate``'s, from each track's first detection). Validation sets only: the choice is made here.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from immnet.data.storage import as_batch, load_dataset
from immnet.evaluation.search import average_rmse
from immnet.tracking.bank import BankMethod

WEIGHINGS = (("filter", 1.0), ("filter", 0.5), ("reported", 1.0), ("reported", 0.5))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", action="append", required=True, help="a validation set with truth (repeat)")
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    sets = {d: as_batch(load_dataset(d)[0]) for d in args.data}
    rows = {}
    for likelihood, temper in WEIGHINGS:
        method = BankMethod(likelihood=likelihood, temper=temper)
        label = f"{likelihood}, temper {temper:g}"
        rows[label] = {}
        for d, batch in sets.items():
            method.check(batch)
            rows[label][d] = average_rmse(method, batch)
            print(f"[weighing] {label} on {d}: {rows[label][d]:.4f} m", file=sys.stderr, flush=True)
    print("| weighing | " + " | ".join(args.data) + " |")
    print("|:---|" + "---:|" * len(args.data))
    for label, cells in rows.items():
        print(f"| {label} | " + " | ".join(f"{cells[d]:.4f}" for d in args.data) + " |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
