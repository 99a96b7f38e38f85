"""What a radar engineer asks of a tracker on plots beyond its RMSE: its worst track and its covariance's honesty.

For each method on a data set's split (as ``immnet evaluate``'s): the pooled RMSE (the mean over x, y, z of each
axis's RMSE over every scored scan, ``immnet.evaluation.metrics.rmse_pooled``), the largest position error of any scan of any track
(3D, metres) with the number of tracks that ever exceed ``--limit-m`` (1 km), and, where the method gives its state's
covariance, the share of scans whose 95 % position ellipsoid holds the truth and the mean NEES (3 when calibrated),
from scan ``--from-scan`` on; and the worst track again counted from each track's ``--from-plot``-th detection on (3:
what a tracker that reports a track once a third plot confirms its start would show; its filter is the same, so its
estimates from then on are too):

    python scripts/radar_report.py --data runs/radar/data/q5-out --methods radar-imm-5s,radar-imm-robust-5s,immnet-bank \\
        --json runs/radar/q5-out-report.json --markdown runs/radar/q5-out-report.md
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def report(method, data, from_scan: int, limit_m: float, from_plot: int = 3) -> dict:
    """One method's row on ``data`` (a TensorDict [N] with ``states``): see the module doc."""
    import torch

    from immnet import keys
    from immnet.evaluation.calibration import coverage, position_nees
    from immnet.evaluation.metrics import position_error, rmse_pooled, scored_distance, scored_mask

    out = method.track(data)
    mask = scored_mask(data[keys.STATES], data[keys.MEASUREMENTS])
    err = position_error(out[keys.STATE], data[keys.STATES])  # [N, T, 3], float64
    dist = scored_distance(err, mask)
    worst = dist.amax(1)  # [N]
    plots = torch.isfinite(data[keys.MEASUREMENTS]).all(-1).cumsum(1)  # [N, T] the track's detections so far
    later = dist.where(plots >= from_plot, torch.zeros((), dtype=dist.dtype)).amax(1)
    row = {"rmse": rmse_pooled(err, mask)["avg"], "worst_m": float(worst.max()), "tracks": int(data.batch_size[0]),
           "tracks_over_limit": int((worst > limit_m).sum()), "from_plot": from_plot,
           "worst_from_plot_m": float(later.max()), "tracks_over_limit_from_plot": int((later > limit_m).sum())}
    if keys.STATE_COV in out.keys():
        nees = position_nees(out[keys.STATE], out[keys.STATE_COV], data[keys.STATES])
        m = mask.clone()
        m[:, :from_scan] = False
        ok = m & torch.isfinite(nees)
        row["coverage_95"] = coverage(nees, m, (0.95,))[0.95]
        row["nees_mean"] = float(nees[ok].mean())
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="a data set directory or .npz (with states, the truth)")
    p.add_argument("--split", choices=("test", "all"), default="test", help="as immnet evaluate's")
    p.add_argument("--methods", required=True, help="comma-separated method names")
    p.add_argument("--from-scan", type=int, default=5, help="the first scan whose coverage is scored (default 5)")
    p.add_argument("--limit-m", type=float, default=1000.0, help="the error a track must never exceed (m, default 1000)")
    p.add_argument("--from-plot", type=int, default=3,
                   help="the worst track counted again from each track's N-th detection on (default 3)")
    p.add_argument("--json", type=Path)
    p.add_argument("--markdown", type=Path)
    args = p.parse_args(argv)

    from immnet.evaluation.cli import load_split
    from immnet.filters.methods import build_method, gives_cov

    data, _ = load_split(args.data, args.split, None)
    rows = {}
    for name in (n.strip() for n in args.methods.split(",") if n.strip()):
        start = time.perf_counter()
        rows[name] = report(build_method(name, return_cov=gives_cov(name)), data, args.from_scan, args.limit_m,
                            args.from_plot)
        print(f"{name}: {rows[name]} [{time.perf_counter() - start:.0f} s]", file=sys.stderr)
    header = (f"| method | pooled RMSE (m) | worst error (m) | tracks over {args.limit_m:g} m | from plot {args.from_plot}: "
              f"worst (m), tracks over | 95 % coverage | mean NEES |")
    lines = [header, "|:---|---:|---:|---:|---:|---:|---:|"]
    for name, r in rows.items():
        cov = f"{r['coverage_95']:.3f}" if "coverage_95" in r else "-"
        nees = f"{r['nees_mean']:.2f}" if "nees_mean" in r else "-"
        lines.append(f"| {name} | {r['rmse']:.1f} | {r['worst_m']:.0f} | {r['tracks_over_limit']} of {r['tracks']} | "
                     f"{r['worst_from_plot_m']:.0f}, {r['tracks_over_limit_from_plot']} | {cov} | {nees} |")
    print("\n".join(lines))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"data": str(args.data), "split": args.split, "from_scan": args.from_scan,
                                         "methods": rows}, indent=1) + "\n")
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
