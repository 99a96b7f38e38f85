"""Where each method's error is, by kind of flight: a real-flight data set's windows grouped by the folder of the
traffic sample their flight comes from (ambulances, calibration, collections, gliders, ...), each group scored as
``immnet evaluate`` scores a set (position RMSE per window, averaged), one run; beside each kind, the share of its
scans in the turn phase (``immnet.evaluation.phases``: the truth's turn rate above 0.5 deg/s).

    python scripts/real_kinds.py --data runs/real/data/heldout-5s/test \\
        --methods real-imm-singer-5s,immnet-real-5s,immnet-general [--checkpoint NAME=CKPT] [--told-r]

The flight of each window is in the set's ``meta.json`` (``window_flights``); its sample is found by reading the
samples the set names again with the set's own cleaning parameters (``immnet.data.adsb``), so the ``traffic``
samples must be installed (``pip install immnet[real]``).
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np

from immnet import keys
from immnet.data.real import set_flights, window_flights
from immnet.data.storage import load_dataset
from immnet.filters.methods import build_method
from immnet.evaluation.phases import phases
from immnet.evaluation.runner import evaluate, to_json
from immnet.imm.guard import parse_guard


def flight_samples(meta: dict) -> dict[str, str]:
    """``{flight id: sample name}`` for the samples ``meta`` names, read with its parameters
    (``immnet.data.real.set_flights``: ``make_adsb``'s reading, naming and selection)."""
    return {f.id: f.sample for f in set_flights(meta)[0]}


def kind(sample: str) -> str:
    """The kind of flight of a sample: the folder it is filed under (``gliders/...`` -> ``gliders``)."""
    return Path(sample).parent.name or sample


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="a real-flight data set (immnet data adsb)")
    p.add_argument("--methods", required=True, help="comma-separated registry names; the first is the ratios' base")
    p.add_argument("--checkpoint", action="append", default=[], metavar="NAME=CKPT")
    p.add_argument("--told-r", action="store_true", help="the networks told each track's r (immnet evaluate --told-r)")
    args = p.parse_args(argv)
    data, meta = load_dataset(args.data)
    owners = window_flights(meta, data.batch_size[0], args.data)
    try:
        samples = flight_samples(meta)
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None
    missing = sorted({f for f in owners if f not in samples})
    if missing:
        raise SystemExit(f"{len(missing)} flight(s) of {args.data} not found in its samples, e.g. {missing[0]}: "
                         f"the samples changed since the set was written")
    kinds = defaultdict(list)
    for i, f in enumerate(owners):
        kinds[kind(samples[f])].append(i)
    ckpts = dict(c.split("=", 1) for c in args.checkpoint)
    names = [n for n in args.methods.split(",") if n]
    methods = {n: build_method(n, ckpts.get(n), guard=parse_guard("none"), told_r=args.told_r) for n in names}
    turning = phases(data[keys.STATES].double())["turn"].numpy()  # the turn phase's scans (docs/notebook/real-flights.md)
    print("| kind (windows, flights) | turning | " + " | ".join(names) + " |")
    print("|:---|---:|" + "---:|" * len(names))
    for group, rows in sorted(kinds.items(), key=lambda kv: -len(kv[1])) + [("all", list(range(len(owners))))]:
        scores = to_json(evaluate(methods, data[np.asarray(rows)], progress=False))
        avg = {n: scores[n]["rmse"]["avg"] for n in names}
        cells = [f"{avg[n]:.3f}" + ("" if n == names[0] else f" ({avg[n] / avg[names[0]]:.3f}x)") for n in names]
        share = f"{100 * turning[np.asarray(rows)].mean():.0f} %"
        print(f"| {group} ({len(rows)}, {len({owners[i] for i in rows})}) | {share} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
