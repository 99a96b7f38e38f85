"""What estimating each track's measurement std r costs a trained IMMNet on a data set with truth: the network with r
estimated scan by scan from the altitude's third differences (docs/immnet.md), told each track's true r, and
told three look-ahead estimates from the whole window (not trackers: references for how much a better estimate from
the same measurements could give): the altitude's, the altitude's trimmed (each difference's square capped at 9 times
the window's median-based estimate), and a trimmed one from all three axes. Then where the cost of the estimate lies:
the windows by how far their whole-window estimate is from the truth.

    python scripts/r_estimate.py --data runs/real/data/heldout-5s/test \\
        --checkpoint immnet/pretrained/immnet-real-5s.ckpt
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from immnet import keys
from immnet.data.storage import load_dataset
from immnet.data.times import scan_intervals
from immnet.evaluation.metrics import per_trajectory_rmse, scored_mask
from immnet.evaluation.runner import evaluate, to_json
from immnet.evaluation.table import format_table
from immnet.tracking.methods import IMMNetMethod

CHI2_MEDIAN = 0.454936  # the median of a chi-square variable with one degree of freedom
BINS = (0.0, 0.8, 0.95, 1.05, 1.2, 1.5, np.inf)


def third_difference_samples(values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``[N, T]``: per scan from the fourth on, the square of the third divided difference of ``values`` at the scan
    times ``t`` over the sum of its squared weights, an unbiased sample of r^2 under CV and CA motion (NaN where a
    detection is missing; the first three NaN); as the network's estimator computes it (``_FilterExperts.noise``)."""
    N, T = values.shape
    out = np.full((N, T), np.nan)
    for k in range(3, T):
        s = t[:, k - 3 : k + 1]
        c = np.ones((N, 4))
        for i in range(4):
            for j in range(4):
                if i != j:
                    c[:, i] /= s[:, i] - s[:, j]
        out[:, k] = (c * values[:, k - 3 : k + 1]).sum(1) ** 2 / (c * c).sum(1)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="a data set with truth and each track's r")
    p.add_argument("--checkpoint", required=True,
                   help="a trained IMMNet (a checkpoint or shipped weights; trained with r estimated or told)")
    args = p.parse_args(argv)
    data, _ = load_dataset(args.data)
    z = data[keys.MEASUREMENTS].double().numpy()
    t = np.cumsum(scan_intervals(data, torch.float64).numpy(), axis=1)
    r = data[keys.R].double().numpy().reshape(-1)
    alt = third_difference_samples(z[..., 2], t)
    whole = np.sqrt(np.nanmean(alt, 1))
    axes = np.concatenate([third_difference_samples(z[..., a], t) for a in range(3)], 1)
    median_based = np.nanmedian(axes, 1) / CHI2_MEDIAN
    trimmed = np.sqrt(np.nanmean(np.minimum(axes, 9 * median_based[:, None]), 1))
    alt_trimmed = np.sqrt(np.nanmean(np.minimum(alt, 9 * np.nanmedian(alt, 1, keepdims=True) / CHI2_MEDIAN), 1))
    q = lambda v: " / ".join(f"{x:.3f}" for x in np.quantile(v / r, [0.1, 0.5, 0.9]))  # noqa: E731
    print(f"whole-window estimate over the truth (10th / 50th / 90th percentile): altitude {q(whole)}, "
          f"altitude trimmed {q(alt_trimmed)}, three axes trimmed {q(trimmed)}")

    estimated = IMMNetMethod(args.checkpoint, "r estimated", r=None)  # as the shipped networks run, however trained
    told = IMMNetMethod(args.checkpoint, "told r", r="data")
    everyone = range(len(r))  # each window's estimates kept, for the cost per window below
    results = evaluate({m.name: m for m in (estimated, told)}, data, progress=False, keep=everyone)
    for name, v in (("told the window's altitude estimate (look-ahead)", whole),
                    ("told the window's trimmed altitude estimate (look-ahead)", alt_trimmed),
                    ("told the window's trimmed 3-axis estimate (look-ahead)", trimmed)):
        looked = data.clone()  # the same windows, each told the look-ahead estimate as its r
        looked.set(keys.R, torch.as_tensor(v, dtype=data[keys.R].dtype))
        results |= evaluate({name: told}, looked, progress=False)
    print(format_table(to_json(results)))

    mask = scored_mask(data[keys.STATES], data[keys.MEASUREMENTS])
    truth = data[keys.STATES][..., [0, 3, 6]].double()
    per = {m.name: per_trajectory_rmse(results[m.name]["kept"][keys.STATE][..., [0, 3, 6]].double() - truth,
                                       mask).numpy() for m in (estimated, told)}
    cost = per[estimated.name] - per[told.name]  # [N, 3] per window and axis, metres
    ratio = whole / r
    print("\nwhere the estimate's cost lies (windows by their whole-window altitude estimate over the truth; the mean "
          "change of the per-window RMSE, metres, and the bin's share of the altitude's total):")
    for lo, hi in zip(BINS, BINS[1:]):
        s = (ratio >= lo) & (ratio < hi)
        if s.any():
            x, y, zc = cost[s].mean(0)
            print(f"  [{lo:.2f}, {hi:.2f}): {int(s.sum()):5d} windows; x {x:+.3f} y {y:+.3f} z {zc:+.3f}; "
                  f"z share {cost[s, 2].sum() / cost[:, 2].sum():.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
