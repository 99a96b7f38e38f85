"""How much a tracker could gain by knowing each track's best noise: a method run over a grid of its settings, the
best setting chosen per window (and per window and axis) with the truth. A reference, not a tracker.

    python scripts/noise_oracle.py --data runs/real/data/quickstart-1s/test --method real-imm-axis \\
        --knob sigma_q.0=0.1,0.2,0.4,0.7,1.0 --knob sigma_q.1=0.2,0.35,0.5,0.7,1.0,1.5 [--json oracle.json]

Rows (docs/notebook/real-flights.md "How far the noise can take a tracker"), each the table's Average RMSE (per window
over its scored scans, then the mean over windows; ``immnet evaluate``'s):

- the method as configured (its YAML in ``configs/methods/``);
- the best single setting of the grid on this set: tuning on the set itself, what a filter tuned on it would give;
- per window: each window scored at the setting best for it, chosen with its truth (a tracker told, for each track,
  the noise level that suits it best, held for the whole window);
- per window and axis: the same per axis. For a method whose axes are filtered apart (``PerAxisIMMTracker``, one
  IMM per axis) each axis's choice is a filter that can run; for a joint one it is a bound only.

Each window's setting is constant over its scans, so this is no bound on a tracker that changes its noise scan by
scan (KalmanNet's); it says how far the choice of noise alone, track by track, could take a filter of this family.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import torch

from immnet import keys
from immnet.config import instantiate, load_yaml
from immnet.data.storage import as_batch, load_dataset
from immnet.filters.methods import method_config
from immnet.evaluation.metrics import per_trajectory_rmse, position_error, scored_mask
from immnet.evaluation.search import Search


def parse_knob(text: str) -> tuple[str, list[float]]:
    """``path=v1,v2,...`` -> ``(path, [v1, v2, ...])``."""
    path, sep, values = text.partition("=")
    if not sep or not path or not values:
        raise ValueError(f"--knob {text!r}: expected PATH=V1,V2,... (a dotted path into the method's init_args)")
    try:
        return path, [float(v) for v in values.split(",")]
    except ValueError:
        raise ValueError(f"--knob {text!r}: the values must be numbers") from None


def per_window(method, batch) -> torch.Tensor:
    """``[N, 3]`` per-window, per-axis RMSE over the scored scans (NaN for a window with none)."""
    with torch.no_grad():
        state = method.track(batch)[keys.STATE]
    truth = batch[keys.STATES]
    return per_trajectory_rmse(position_error(state, truth), scored_mask(truth, batch[keys.MEASUREMENTS]))


def oracle(errors: torch.Tensor) -> dict[str, float]:
    """From ``errors [S, N, 3]`` (settings, windows, axes): the best single setting, per window, per window and axis
    (each the mean over windows of the mean over axes)."""
    keep = torch.isfinite(errors).all(-1).all(0)
    e = errors[:, keep]
    single = e.mean(-1).mean(-1)
    return {
        "best_single": float(single.min()),
        "best_single_index": int(single.argmin()),
        "per_window": float(e.mean(-1).min(0).values.mean()),
        "per_window_axis": float(e.min(0).values.mean(-1).mean()),
        "windows": int(keep.sum()),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="a data set with truth (a split directory)")
    p.add_argument("--method", required=True, help="a registry name with a config in configs/methods/")
    p.add_argument("--knob", action="append", required=True, metavar="PATH=V1,V2,...",
                   help="a dotted path into the method's init_args and the values to try (repeat: their product)")
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    try:
        knobs = dict(parse_knob(k) for k in args.knob)
        config = load_yaml(method_config(args.method))
        grid = Search(config, knobs)  # immnet tune's search file: checks each knob is a path into init_args
    except ValueError as e:
        print(f"error: {args.method}: {e}", file=sys.stderr)
        return 2
    td, _ = load_dataset(args.data)
    batch = as_batch(td)
    configured = per_window(instantiate(config), batch)
    settings = [dict(zip(knobs, values)) for values in itertools.product(*knobs.values())]
    errors = []
    for i, setting in enumerate(settings):
        errors.append(per_window(instantiate(grid.config(setting)), batch))
        print(f"[oracle] {i + 1}/{len(settings)} {setting}: {float(errors[-1].mean(-1).nanmean()):.4f} m",
              file=sys.stderr, flush=True)
    result = oracle(torch.stack(errors))
    keep = torch.isfinite(configured).all(-1)
    result["configured"] = float(configured[keep].mean(-1).mean())
    result["best_single_setting"] = settings[result.pop("best_single_index")]
    base = result["configured"]
    rows = [("as configured", base), (f"best single setting {result['best_single_setting']}", result["best_single"]),
            ("per window (oracle)", result["per_window"]), ("per window and axis (oracle)", result["per_window_axis"])]
    print(f"| {args.method} on {args.data} ({result['windows']} windows) | Average [m] | / as configured |")
    print("|:---|---:|---:|")
    for label, value in rows:
        print(f"| {label} | {value:.3f} | {value / base:.3f}x |")
    if args.json:
        args.json.write_text(json.dumps({"data": args.data, "method": args.method, "knobs": knobs, **result},
                                        indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
