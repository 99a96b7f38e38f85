"""``immnet track --input FILE --output FILE [--checkpoint CKPT]``: estimates for your own measurements."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "track",
        help="track your own measurements (CSV track_id,t,x,y,z or .npz) with a trained IMMNet",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--input", required=True, type=Path, help="CSV (track_id,t,x,y,z) or .npz with measurements [N,T,3]")
    p.add_argument("--output", required=True, type=Path, help="CSV or .npz (same kind as the input)")
    p.add_argument("--checkpoint", default=None, help="Lightning checkpoint (default: the shipped weights)")
    p.add_argument(
        "--guard", default="checkpoint",
        help="range guard: 'checkpoint' (as trained; the shipped weights: 3D-LAST's region, turns back beyond 33 km "
             "and within 4 km, and its speed envelope, 40-330 m/s), 'none' (data from another region), or "
             "'OUTER,INNER' in metres (another region, 3D-LAST's speed envelope)",
    )
    p.add_argument(
        "--adapt", action="store_true",
        help="adaptive process noise in the filter experts (immnet.filters.adaptive.AdaptiveNoise): for targets "
             "that fly rougher than the training data (docs/immnet.md, 'Adaptive process noise')",
    )
    p.set_defaults(func=run)


def parse_guard(text: str):
    """``--guard``: ``checkpoint``, ``none`` or ``OUTER,INNER`` (metres) -> ``load_network``'s guard."""
    from immnet.tracking.tracker import KEEP

    text = text.strip().lower()
    if text == KEEP:
        return KEEP
    if text == "none":
        return None
    try:
        outer, inner = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--guard must be 'checkpoint', 'none' or 'OUTER,INNER' in metres, got {text!r}") from None
    return {"outer": outer, "inner": inner}


def run(args) -> int:
    from immnet.tracking.tracker import KEEP, PRETRAINED, Tracker

    tracker = Tracker.from_checkpoint(args.checkpoint or PRETRAINED, parse_guard(args.guard), True if args.adapt else KEEP)
    suffix_in, suffix_out = args.input.suffix.lower(), args.output.suffix.lower()
    if suffix_in not in (".csv", ".npz") or suffix_out != suffix_in:
        raise ValueError(f"--input and --output must both be .csv or both .npz (got {args.input.name}, {args.output.name})")
    if suffix_in == ".csv":
        from immnet.tracking.io import read_tracks_csv, write_tracks_csv

        ids, z, rows = read_tracks_csv(args.input, tracker.net.dt)
        out = tracker.track(z)
        write_tracks_csv(args.output, rows, out["state"].numpy(), out["mode_probs"].numpy())
        print(f"tracked {len(ids)} tracks, {len(rows)} scans -> {args.output}", file=sys.stderr)
        return 0
    from immnet.data.storage import load_dataset

    from immnet.tracking.methods import check_dt

    data, _ = load_dataset(args.input)
    check_dt(tracker.net, data["dt"], "the checkpoint")
    out = tracker.track(data["measurements"])
    tmp = args.output.with_name(args.output.stem + ".partial.npz")
    np.savez(tmp, state=out["state"].numpy(), mode_probs=out["mode_probs"].numpy(), dt=np.float64(tracker.net.dt))
    tmp.replace(args.output)
    print(f"tracked {out.batch_size[0]} tracks -> {args.output}", file=sys.stderr)
    return 0
