"""The validation table of the radar networks (scripts/radar_range.sh): from RUN/val-*.json (one `immnet evaluate`
run per validation split, the band's two filters told each plot's covariance and its network in one run), one row per
set: each method's Average RMSE (m) and the network's ratio to the better of the two filters.

Run:  python scripts/radar_range_table.py runs/radar-range > runs/radar-range/validation.md
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

SETS = {"q{s}-clean": "one radar (40 m, 0.12 / 0.2 deg, 10-100 km), clean",
        "q{s}-out": "one radar, 2 % outliers at 10x",
        "r{s}-clean": "radars 10-80 m, 0.03-0.3 deg, 5-150 km, clean",
        "r{s}-out5": "radars as trained, 1 % outliers at 5x",
        "r{s}-out10": "radars as trained, 3 % outliers at 10x",
        "r{s}-out20": "radars as trained, 5 % outliers at 20x",
        "x{s}-range100": "unseen: range std 100 m, clean",
        "x{s}-angle0.4": "unseen: angle stds 0.4 deg, 3 % outliers at 10x"}


def main(run: str) -> int:
    run = Path(run)
    print("| scans | validation set | tracks | radar-imm | radar-imm-robust | network | network / best filter |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for s, band in ((5, "4.5-5.5 s"), (11, "10-12 s")):
        for key, what in SETS.items():
            name = key.format(s=s)
            found = sorted(run.glob(f"val-*-{name}.json"))
            if not found:
                continue
            d = json.loads(found[0].read_text())
            m = {k: v["rmse"]["avg"] for k, v in d["methods"].items()}
            plain, robust, net = m[f"radar-imm-{s}s"], m[f"radar-imm-robust-{s}s"], m[f"immnet-radar-{s}s"]
            print(f"| {band} | {name}/val: {what} | {d['n_trajectories']} | {plain:.1f} | {robust:.1f} | {net:.1f} | "
                  f"{net / min(plain, robust):.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
