"""A real flight as the trackers see it: its track seen from above and its altitude, with the measurements and each
method's estimates, and each method's position error over time (the README's real-flight figure).

    python scripts/real_figure.py --data runs/real/data/quickstart-1s/test --methods real-imm-axis,immnet-real \\
        --checkpoint immnet-real=runs/real/axis/checkpoints/best.ckpt --out runs/real/figures/real_flight.png

The window shown is the test window whose truth climbs or descends the most while it turns (``--index`` picks
another); the methods run on the whole test set's window alone, as they would on a user's data.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from immnet import keys  # noqa: E402
from immnet.data.storage import as_batch, load_dataset  # noqa: E402
from immnet.data.times import scan_intervals  # noqa: E402
from immnet.evaluation.figures import method_colors  # noqa: E402
from immnet.filters.methods import build_method  # noqa: E402
from immnet.imm.guard import parse_guard  # noqa: E402


def pick_window(batch) -> int:
    """The window that climbs or descends the most while it turns: max over windows of
    (altitude change in m) x (heading change in rad)."""
    s = batch[keys.STATES].to(torch.float64)
    climb = (s[:, :, 6].amax(1) - s[:, :, 6].amin(1))
    heading = torch.atan2(s[:, :, 4], s[:, :, 1])
    turn = torch.remainder(heading.diff(dim=1) + np.pi, 2 * np.pi).sub(np.pi).abs().sum(1)
    return int(torch.argmax(climb * turn))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--methods", required=True, help="comma-separated registry names")
    p.add_argument("--checkpoint", action="append", default=[], metavar="NAME=CKPT")
    p.add_argument("--index", type=int, help="the window to show (default: pick_window's)")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    td, _ = load_dataset(args.data)
    batch = as_batch(td, torch.float64)
    i = pick_window(batch) if args.index is None else args.index
    one = batch[i : i + 1]
    ckpts = dict(c.split("=", 1) for c in args.checkpoint)
    names = args.methods.split(",")
    est = {}
    for name in names:
        method = build_method(name, ckpts.get(name), guard=parse_guard("none"))
        est[name] = method.track(one.to(torch.float32))[keys.STATE][0].to(torch.float64).numpy()  # as evaluate hands it
    truth, z = one[keys.STATES][0].numpy(), one[keys.MEASUREMENTS][0].numpy()
    t = torch.cumsum(scan_intervals(one)[0], 0).numpy()
    t = t - t[0]
    colors = method_colors(names)
    fig, ax = plt.subplots(1, 3, figsize=(16, 4.6))
    ax[0].plot(z[:, 0] / 1e3, z[:, 1] / 1e3, ".", ms=2, color="0.6", label="measurements")
    ax[0].plot(truth[:, 0] / 1e3, truth[:, 3] / 1e3, "k-", lw=1.5, label="truth (smoothed ADS-B)")
    ax[1].plot(t, z[:, 2], ".", ms=2, color="0.6")
    ax[1].plot(t, truth[:, 6], "k-", lw=1.5)
    for name in names:
        e = est[name]
        ax[0].plot(e[:, 0] / 1e3, e[:, 3] / 1e3, "-", lw=1, color=colors[name], label=name)
        ax[1].plot(t, e[:, 6], "-", lw=1, color=colors[name])
        err = np.linalg.norm(e[:, 0::3] - truth[:, 0::3], axis=-1)
        ax[2].plot(t, err, "-", lw=1, color=colors[name], label=f"{name} (RMSE {np.sqrt(np.nanmean(err[10:] ** 2)):.2f} m)")
    raw = np.linalg.norm(z - truth[:, 0::3], axis=-1)
    ax[2].plot(t, raw, ".", ms=2, color="0.6", label=f"measurements (RMSE {np.sqrt(np.nanmean(raw[10:] ** 2)):.2f} m)")
    ax[0].set(xlabel="east [km]", ylabel="north [km]", title=f"real flight, test window {i}: from above")
    ax[0].set_aspect("equal", adjustable="datalim")
    ax[1].set(xlabel="time [s]", ylabel="height above the radar [m]", title="altitude")
    ax[2].set(xlabel="time [s]", ylabel="3D position error [m]", title="error over time", ylim=(0, np.nanpercentile(raw, 99)))
    ax[0].legend(fontsize=8)
    ax[2].legend(fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out} (window {i})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
