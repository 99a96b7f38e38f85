"""Where each method's error is, by flight phase (``immnet.evaluation.phases``): level, turn, climb/descent, speed
change, on a real-flight data set.

    python scripts/real_phases.py --data runs/real/data/quickstart-1s/test --methods real-imm-axis,immnet-real \\
        --checkpoint immnet-real=runs/real/axis/checkpoints/best.ckpt [--json phases.json] [--markdown phases.md]

``--config LABEL=PATH`` adds a row for a method config that is not in the registry (a YAML with ``class_path`` and
``init_args``, as in ``configs/methods/``), e.g. the variants of ``configs/studies/``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from immnet import keys
from immnet.config import instantiate, load_yaml
from immnet.data.storage import as_batch, load_dataset
from immnet.filters.methods import build_method
from immnet.evaluation.metrics import scored_mask
from immnet.evaluation.phases import PHASES, rmse_by_phase
from immnet.imm.guard import parse_guard


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--methods", default="", help="comma-separated registry names")
    p.add_argument("--config", action="append", default=[], metavar="LABEL=PATH",
                   help="a row for the method config at PATH (class_path, init_args), labelled LABEL")
    p.add_argument("--checkpoint", action="append", default=[], metavar="NAME=CKPT")
    p.add_argument("--json", type=Path)
    p.add_argument("--markdown", type=Path)
    args = p.parse_args(argv)
    configs = {}
    for c in args.config:
        label, sep, path = c.partition("=")
        if not sep or not label or not Path(path).is_file():
            p.error(f"--config {c!r}: expected LABEL=PATH of a method config file")
        configs[label] = path
    names = [n for n in args.methods.split(",") if n]
    if not names and not configs:
        p.error("nothing to score: give --methods and/or --config")
    td, _ = load_dataset(args.data)
    ckpts = dict(c.split("=", 1) for c in args.checkpoint)
    rows = {}
    batch = as_batch(td)  # as immnet evaluate hands it to every method (each computes in its own dtype)
    for name in names + list(configs):
        if name in configs:
            method = instantiate(load_yaml(configs[name]))
        else:
            method = build_method(name, ckpts.get(name), guard=parse_guard("none"))
        with torch.no_grad():
            state = method.track(batch)[keys.STATE].to(torch.float64)
        truth = batch[keys.STATES].to(torch.float64)
        rows[name] = rmse_by_phase(state, truth, scored_mask(truth, batch[keys.MEASUREMENTS]))
    first = next(iter(rows.values()))
    head = "| method | " + " | ".join(f"{ph} [m] ({100 * first[ph]['share']:.0f} %)" for ph in PHASES) + " |"
    lines = [head, "|:---|" + "---:|" * len(PHASES)]
    for name, r in rows.items():
        lines.append(f"| {name} | " + " | ".join("-" if r[ph]["rmse"] is None else f"{r[ph]['rmse']:.3f}" for ph in PHASES) + " |")
    table = "\n".join(lines)
    print(table)
    if args.markdown:
        args.markdown.write_text(table + "\n")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2, allow_nan=False) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
