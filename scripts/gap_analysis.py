"""Where IMMNet loses to the clairvoyant bound: pooled position RMSE (per axis) by true mode, by noise
level and by time since the last mode switch, beside each expert's own posterior, the "oracle pick"
(the posterior of the true mode's expert) and the mean probability on the true mode. Last, in the
metric's own terms (docs/spec.md section 5, all scans): the Average RMSE if IMMNet's errors were the
bound's in one group of scans (start, after a switch, steady flight per mode), i.e. what closing the
gap there would buy.

``--alone DATA...`` instead runs each expert alone (as in stage 1: its own posterior is its
estimate) on single-mode data sets (``immnet data generate --single-mode ca ...``) and prints each
expert's ratio to the bound: all scans in the metric's terms, and pooled over the scans from 20 on
that are still in the first segment (before any soft-bound turn). It tells an expert's own
quality as a filter apart from the mixing.

Run (after `bash scripts/main.sh`):
    .venv/bin/python scripts/gap_analysis.py [--checkpoint runs/quick/stage2/checkpoints/best.ckpt]
        [--data runs/quick/data/test] [--n 1000]
Scans from 20 on (the tracks' start is excluded). Needs states, mode, turn_rate and r in the data.
"""

from __future__ import annotations

import argparse

import torch

from immnet import keys
from immnet.data.storage import as_batch, load_dataset
from immnet.evaluation.metrics import per_trajectory_rmse, position_error
from immnet.filters.clairvoyant import ClairvoyantKF
from immnet.motion import MODE_NAMES
from immnet.tracking.tracker import load_network


def table_average(err: torch.Tensor) -> float:
    """The README table's Average RMSE of position errors ``[N, T, 3]`` (docs/spec.md section 5)."""
    return per_trajectory_rmse(err).mean().item()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", default="runs/quick/stage2/checkpoints/best.ckpt")
    p.add_argument("--data", default="runs/quick/data/test")
    p.add_argument("--n", type=int, default=1000)
    p.add_argument("--alone", nargs="+", metavar="DATA", help="single-mode data sets: each expert alone on each")
    a = p.parse_args()
    torch.set_grad_enabled(False)
    net = load_network(a.checkpoint)
    if a.alone:
        experts_alone(net, a.alone, a.n, a.checkpoint)
        return
    td, _ = load_dataset(a.data)
    b = as_batch(td[: a.n])
    z, truth, mode, r = b[keys.MEASUREMENTS], b[keys.STATES], b[keys.MODE], b[keys.R]
    out, _ = net.rollout(z)
    post, fused = out[keys.ROLLOUT_EXPERT_POST], out[keys.STATE]
    prob = net.to_mode_probs(out[keys.ROLLOUT_EXPERT_PROBS])
    bound = ClairvoyantKF().track(b)[keys.STATE].float()

    err_f, err_c = position_error(fused, truth), position_error(bound, truth)  # [N, T, 3]
    ef, ec = err_f.square().sum(-1), err_c.square().sum(-1)  # squared 3D position errors [N, T]
    M = post.shape[2]
    ee = torch.stack([position_error(post[:, :, i], truth).square().sum(-1) for i in range(M)], -1)
    expert_mode = net.mode_onehot.argmax(-1)  # the data mode of each expert
    pick = None  # the squared error of the true mode's (first) expert, where every mode has one
    if all(bool((expert_mode == m).any()) for m in range(len(MODE_NAMES))):
        own = torch.stack([(expert_mode == m).nonzero()[0, 0] for m in range(len(MODE_NAMES))])
        pick = ee.gather(-1, own[mode].unsqueeze(-1)).squeeze(-1)
    p_true = prob.gather(-1, mode.unsqueeze(-1)).squeeze(-1)
    since, prev = torch.zeros_like(mode), torch.full_like(mode, -1)  # scans since the last switch, mode before it
    for t in range(1, mode.shape[1]):
        same = mode[:, t] == mode[:, t - 1]
        since[:, t] = torch.where(same, since[:, t - 1] + 1, 0)
        prev[:, t] = torch.where(same, prev[:, t - 1], mode[:, t - 1])
    late = torch.zeros_like(mode, dtype=torch.bool)
    late[:, 20:] = True

    def rms(e, m):
        return (e[m].mean() / 3).sqrt().item()

    def ratio(m):  # IMMNet / bound over the scans of mask m
        return rms(ef, m) / rms(ec, m)

    print(f"{a.checkpoint} on {z.shape[0]} trajectories of {a.data}; pooled RMSE per axis [m], scans >= 20")
    print("experts: " + ", ".join(net.model_set.names))
    for label, rm in (("r <= 4 m", r <= 4), ("r > 4 m", r > 4)):
        print(label)
        for k, name in enumerate(MODE_NAMES):
            m = late & (mode == k) & rm[:, None]
            line = f"  {name:4s} fused {rms(ef, m):.3f} bound {rms(ec, m):.3f}"
            if pick is not None:
                line += f" oracle-pick {rms(pick, m):.3f}"
            line += " experts " + " ".join(f"{rms(ee[..., i], m):.3f}" for i in range(M))
            line += f"  p(true mode) {p_true[m].mean():.3f}"
            print(line)
    print("by scans since the last switch: fused / bound (ratio), and each mode; excess = share of the MSE excess")
    total = (ef - ec)[late].sum()
    for lo, hi in ((0, 5), (5, 10), (10, 20), (20, 40), (40, 10**6)):
        m = late & (since >= lo) & (since < hi)
        print(f"  [{lo}, {hi if hi < 10**6 else 'end'}) n={int(m.sum())} {rms(ef, m):.3f} / {rms(ec, m):.3f} "
              f"({ratio(m):.3f}) excess {float((ef - ec)[m].sum() / total):.0%}  "
              + " ".join(f"{n} {ratio(m & (mode == k)):.3f}"
                         for k, n in enumerate(MODE_NAMES) if bool((m & (mode == k)).any())))

    print("the 20 scans after a switch, by switch: fused / bound (ratio), share of the MSE excess; "
          "p(true mode) and fused / bound at 0, 2, 5 and 10 scans after it")
    for a_ in range(4):
        for b_ in range(4):
            m = late & (since < 20) & (prev == a_) & (mode == b_)
            if not bool(m.any()):
                continue
            at = []
            for s_ in (0, 2, 5, 10):
                ms = m & (since == s_)
                at.append(f"{p_true[ms].mean():.2f}/{ratio(ms):.2f}" if bool(ms.any()) else "-")
            print(f"  {MODE_NAMES[a_]:>3s} -> {MODE_NAMES[b_]:3s} n={int(m.sum()):6d} {ratio(m):.3f} "
                  f"excess {float((ef - ec)[m].sum() / total):.1%}  " + " ".join(at))

    # by measurement noise: the metric (mean per-trajectory RMSE, all scans) per bin of r, and what
    # knowing r is worth to the bound (the same KF told r = 4 m for every trajectory)
    b4 = b.clone()
    b4.set(keys.R, torch.full_like(r, 4.0))
    err_4 = position_error(ClairvoyantKF().track(b4)[keys.STATE].float(), truth)
    tf, tc, t4 = (per_trajectory_rmse(e).mean(-1) for e in (err_f, err_c, err_4))  # Average per trajectory [N]
    print("by measurement noise r: Average RMSE of IMMNet / bound, and the bound told r = 4 m / bound")
    for lo in range(1, 7):
        m = (r >= lo) & (r < lo + 1)
        if bool(m.any()):
            print(f"  r in [{lo}, {lo + 1}) m n={int(m.sum()):4d} IMMNet {tf[m].mean():.3f} / bound "
                  f"{tc[m].mean():.3f} ({tf[m].mean() / tc[m].mean():.3f}); bound at r = 4: "
                  f"{t4[m].mean() / tc[m].mean():.3f}; share of the excess "
                  f"{float((tf - tc)[m].sum() / (tf - tc).sum()):.0%}")

    full, floor = table_average(err_f), table_average(err_c)  # the metric itself: all scans count
    print(f"the Average RMSE (all scans) {full:.3f} m, {full / floor:.3f}x the bound's {floor:.3f} m; "
          "with the bound's errors in place of IMMNet's in one group of scans:")
    after = (since < 20) & (since < torch.arange(mode.shape[1]))  # a switch inside the track, not its start
    groups = {
        "scans 0-19 of the track": ~late,
        "0-4 scans after a switch": late & after & (since < 5),
        "5-19 scans after a switch": late & after & (since >= 5),
    }
    for k, name in enumerate(MODE_NAMES):
        groups[f"steady {name} (20+ scans on)"] = late & ~after & (mode == k)
    for label, m in groups.items():
        print(f"  {label:28s} share {float(m.float().mean()):.3f}: "
              f"{table_average(torch.where(m[..., None], err_c, err_f)) / floor:.3f}x")


def experts_alone(net, datasets, n: int, checkpoint: str) -> None:
    """Each expert of ``net`` alone on each data set: its ratio to the clairvoyant bound."""
    M = net.n_experts
    print(f"{checkpoint}: each expert alone / bound, all scans (metric) and steady first segment (pooled, scans >= 20)")
    for data in datasets:
        td, _ = load_dataset(data)
        b = as_batch(td[:n])
        z, truth, mode = b[keys.MEASUREMENTS], b[keys.STATES], b[keys.MODE]
        out, _ = net.rollout(z.unsqueeze(1).expand(-1, M, -1, -1).contiguous(), experts_alone=True)
        steady = (mode == mode[:, :1]).cumprod(1).bool()  # still in the first segment
        steady[:, :20] = False

        def scores(x):  # (the metric, pooled RMSE over the steady scans)
            err = position_error(x, truth)
            return table_average(err), err.square()[steady].mean().sqrt().item()

        full_c, steady_c = scores(ClairvoyantKF().track(b)[keys.STATE].float())
        cells = []
        for i, name in enumerate(net.model_set.names):
            full_i, steady_i = scores(out[keys.STATE][:, :, i])
            cells.append(f"{name} {full_i / full_c:.3f} / {steady_i / steady_c:.3f}")
        print(f"  {data} ({z.shape[0]} trajectories): " + "  ".join(cells))


if __name__ == "__main__":
    main()
