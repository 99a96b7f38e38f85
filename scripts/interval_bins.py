"""Each method's RMSE by the scan's interval (the time since the scan before), on a data set with per-scan
intervals: where in 0.5-12 s a tracker gains or loses.

    python scripts/interval_bins.py --data runs/general/data/test-0.5-12s --methods imm-ekf-general,immnet-general \
        [--knock-out immnet-general]

``--knock-out NAME`` adds the rows of that registry network with its learned parts knocked out
(``scripts/learned_parts.py``'s variants: ``IMMNet.knock_out``, no training again).

The scans ``immnet evaluate`` scores (``scored_mask``), binned by their interval (``--edges``, seconds); in each bin
each axis's RMSE pooled over the bin's scans of every track (``metrics.rmse_by_interval``: a bin holds a part of
each track's scans, so the per-track RMSE ``immnet evaluate`` averages is not taken), then the mean over x, y, z.
"""

from __future__ import annotations

import argparse

from immnet.config import load_yaml, resolve_path
from immnet.data.storage import load_dataset
from immnet.filters.methods import build_method
from immnet.evaluation.metrics import interval_bin
from immnet.evaluation.runner import evaluate_by_interval
from immnet.tracking.methods import IMMNetMethod


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--methods", required=True, help="comma-separated registry names")
    p.add_argument("--checkpoint", action="append", default=[], metavar="NAME=CKPT",
                   help="another run of registry network NAME, as immnet evaluate's --checkpoint")
    p.add_argument("--knock-out", default="", help="a registry network whose knocked-out variants get rows too")
    p.add_argument("--edges", default="0.5,2,4,6,8,10,12", help="bin edges in seconds (the last bin holds its edge)")
    args = p.parse_args(argv)
    edges = [float(v) for v in args.edges.split(",")]
    try:
        interval_bin([], edges)  # the edges' one check (metrics.interval_bin), before any data is read
    except ValueError as err:
        raise SystemExit(f"--edges {args.edges!r}: {err}") from None
    td, _ = load_dataset(args.data)
    bins = list(zip(edges[:-1], edges[1:]))
    print("| method | " + " | ".join(f"{lo:g}-{hi:g} s [m]" for lo, hi in bins) + " |")
    print("|:---|" + "---:|" * len(bins))
    ckpts = dict(c.split("=", 1) for c in args.checkpoint)
    methods = {name: build_method(name, checkpoint=ckpts.get(name)) for name in args.methods.split(",") if name}
    if args.knock_out:
        import runpy
        from pathlib import Path

        variants = runpy.run_path(str(Path(__file__).with_name("learned_parts.py")))["variants"]
        config = load_yaml(resolve_path(f"configs/methods/{args.knock_out}.yaml"))
        if not config["class_path"].endswith("IMMNetMethod"):
            raise SystemExit(f"--knock-out {args.knock_out}: not a registry IMMNet")
        checkpoint = ckpts.get(args.knock_out) or str(resolve_path(config["init_args"]["checkpoint"]))
        from immnet.tracking.tracker import load_network

        for suffix, parts in variants(load_network(checkpoint).learned_parts()).items():
            if parts:
                init = {**config["init_args"], "name": args.knock_out + suffix, "knock_out": parts,
                        "checkpoint": checkpoint}
                methods[init["name"]] = IMMNetMethod(**init)
    for name, row in evaluate_by_interval(methods, td, edges):
        if name == "scans":
            print(f"\nscans per bin: {row}")
        else:
            print(f"| {name} | " + " | ".join("-" if v is None else f"{v:.3f}" for v in row) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
