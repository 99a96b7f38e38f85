"""Each method's Average RMSE by the scan's interval (the time since the scan before), on a data set with
per-scan intervals: where in 0.5-12 s a tracker gains or loses.

    python scripts/interval_bins.py --data runs/general/data/test-0.5-12s --methods imm-ekf-general,immnet-general

The scans ``immnet evaluate`` scores (``scored_mask``), binned by their interval (``--edges``, seconds); in each bin
the mean over x, y, z of each axis's RMSE (``immnet evaluate``'s Average).
"""

from __future__ import annotations

import argparse

import torch

from immnet import keys
from immnet.data.storage import as_batch, load_dataset
from immnet.data.times import scan_intervals
from immnet.evaluation.methods import build_method
from immnet.evaluation.metrics import position_error, scored_mask


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--methods", required=True, help="comma-separated registry names")
    p.add_argument("--edges", default="0.5,2,4,6,8,10,12", help="bin edges in seconds (the last bin holds its edge)")
    args = p.parse_args(argv)
    edges = [float(v) for v in args.edges.split(",")]
    if len(edges) < 2 or any(b <= a for a, b in zip(edges, edges[1:])):
        raise SystemExit(f"--edges must be at least two increasing numbers, got {args.edges!r}")
    td, _ = load_dataset(args.data)
    batch = as_batch(td, torch.float64)
    dt = scan_intervals(batch, torch.float64, None)
    mask = scored_mask(batch[keys.STATES], batch[keys.MEASUREMENTS])
    bins = list(zip(edges[:-1], edges[1:]))
    print("| method | " + " | ".join(f"{lo:g}-{hi:g} s [m]" for lo, hi in bins) + " |")
    print("|:---|" + "---:|" * len(bins))
    counts = []
    for name in args.methods.split(","):
        with torch.no_grad():
            e2 = position_error(build_method(name).track(batch)[keys.STATE], batch[keys.STATES]) ** 2
        cells = []
        for i, (lo, hi) in enumerate(bins):
            sel = mask & (dt >= lo) & ((dt <= hi) if i == len(bins) - 1 else (dt < hi))
            counts.append(int(sel.sum()))
            cells.append(f"{e2[sel].mean(0).sqrt().mean():.3f}" if sel.any() else "-")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
    print(f"\nscans per bin: {counts[:len(bins)]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
