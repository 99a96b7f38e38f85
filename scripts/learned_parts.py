"""What each learned part of a trained IMMNet is worth on a data set: the network as trained and with each of its
learned parts knocked out (KalmanNet's noise and gain corrections: the filter experts at their base noise; the
Transformer's correction: the IMM's mode update alone; the output correction: the filters' own estimate), and with
all of them (IMMNet with nothing learned: a model-based IMM), in one run beside the model-based filters given
(``IMMNet.knock_out``: no training again, so each row is the trained network minus that part). Only the parts the
network has with parameters are rows (``IMMNet.learned_parts``: a correction on model-based filters has one). Real
flights carry no range guard.

    python scripts/learned_parts.py --data runs/real/data/quickstart-1s/test --checkpoint runs/general/fit/checkpoints/best.ckpt \\
        --label immnet-general --baselines real-imm-axis,real-imm [--json parts.json] [--markdown parts.md]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from immnet.data.storage import load_dataset
from immnet.filters.methods import build_method
from immnet.evaluation.runner import evaluate, to_json
from immnet.evaluation.table import format_markdown, format_table
from immnet.imm.guard import parse_guard
from immnet.tracking.methods import IMMNetMethod

PARTS = {  # IMMNet.knock_out's part (IMMNet.PARTS) -> its row's suffix
    "gain": " - KalmanNet (filters at base noise)",
    "classifier": " - Transformer (IMM mode update alone)",
    "correction": " - output correction (the filters' estimate)",
}


def variants(parts: list[str]) -> dict[str, tuple[str, ...]]:
    """Row suffix -> the learned parts knocked out: none, each alone, and all of them where there are several."""
    rows = {"": ()} | {PARTS[part]: (part,) for part in parts}
    if len(parts) > 1:
        rows[" - both (nothing learned)" if len(parts) == 2 else " - all (nothing learned)"] = tuple(parts)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="a data set with truth (a directory or .npz)")
    p.add_argument("--checkpoint", required=True, help="the trained IMMNet (a Lightning checkpoint or shipped weights)")
    p.add_argument("--label", default="immnet", help="the network's row label")
    p.add_argument("--baselines", default="", help="comma-separated registry methods to score beside it")
    p.add_argument("--guard", default="none", help="range guard of every method (parse_guard): none on real flights")
    p.add_argument("--json", type=Path)
    p.add_argument("--markdown", type=Path)
    args = p.parse_args(argv)
    data, _ = load_dataset(args.data)
    guard = parse_guard(args.guard)
    methods = {name: build_method(name, guard=guard) for name in args.baselines.split(",") if name}
    from immnet.tracking.tracker import load_network

    for suffix, parts in variants(load_network(args.checkpoint).learned_parts()).items():
        methods[args.label + suffix] = IMMNetMethod(args.checkpoint, args.label + suffix, guard=guard, knock_out=parts)
    rows = to_json(evaluate(methods, data, progress=True))
    print(format_table(rows))
    if args.markdown:
        args.markdown.write_text(format_markdown(rows) + "\n")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2, allow_nan=False) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
