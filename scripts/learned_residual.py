"""A learned output correction of a model-based filter, trained over whole sequences outside the step: quick trials of
what a causal network that sees a track's whole history can add to the best filter (the product's form is
``IMMNet(correction=...)``, trained by ``immnet fit``, e.g. ``recipes/real-singer-output.yaml``).

    python scripts/learned_residual.py --train runs/real/data/quickstart-1s/train --val runs/real/data/quickstart-1s/val \\
        --test runs/real/data/quickstart-1s/test --test runs/real/data/heldout-1s/test --method real-imm-singer

The filter (a registry method with a covariance, told each track's r) tracks each window; a GRU reads, scan by
scan, what the filter knows after that scan (its estimate's distance to the measurement, velocity, acceleration,
standard deviations and mode probabilities, each track's r and the scan's interval: nothing absolute, so nothing of
where the flight is) and adds a correction to the filter's position, ``x_hat + r * g(history)``. The GRU sees only
scans up to t, so the corrected estimate is causal: a tracker in its own right. Trained on the training flights, each epoch on fresh views of them (``FlightAugment``:
turned about the site and measured again with their own r, the filter run again on each view), the epoch chosen on
the validation flights, then each test set once. Scored as ``immnet evaluate`` scores (per window over its scored
scans, then the mean over windows). The network is ``immnet.stages.correct.OutputCorrection``'s, weights of the same
names, run over whole sequences outside the step (docs/immnet.md "The output correction").
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
from torch import nn

from immnet import keys
from immnet.config import instantiate, load_yaml
from immnet.data.augment import FlightAugment
from immnet.data.storage import as_batch, load_dataset
from immnet.data.times import scan_intervals
from immnet.filters.methods import method_config
from immnet.evaluation.metrics import AXES, position_error, rmse, scored_mask
from immnet.motion import ACC, POS, VEL

VEL_SCALE, ACC_SCALE = 100.0, 1.0


def filter_features(method, batch) -> tuple[torch.Tensor, torch.Tensor]:
    """The filter's estimate ``[B, T, 9]`` and the network's input ``[B, T, F]`` (float64), each scan's from that
    scan's filter output alone."""
    with torch.no_grad():
        out = method.track(batch)
    state = out[keys.STATE].double()
    cov = out[keys.STATE_COV].double()
    probs = out[keys.EXPERT_PROBS].double()  # [B, T, 3, M]
    z = batch[keys.MEASUREMENTS].double()
    B, T, _ = z.shape
    r = batch[keys.R].double().reshape(B, 1, 1).expand(B, T, 1)
    var = cov.diagonal(dim1=-2, dim2=-1).clamp_min(0)
    seen = torch.isfinite(z).all(-1, keepdim=True)
    d = torch.where(seen, (z - state[..., list(POS)]) / r, torch.zeros_like(z))
    dt = scan_intervals(batch).double().reshape(-1, T, 1).expand(B, T, 1)
    feats = torch.cat([
        d, seen.double(),
        state[..., list(VEL)] / VEL_SCALE, state[..., list(ACC)] / ACC_SCALE,
        var[..., list(POS)].sqrt() / r, var[..., list(VEL)].sqrt(), var[..., list(ACC)].sqrt(),
        probs.reshape(B, T, -1), r / 5.0, dt.log(),
    ], -1)
    started = seen.cumsum(1) > 0
    feats = torch.where(started & torch.isfinite(feats), feats, torch.zeros_like(feats))
    return state, feats


class Residual(nn.Module):
    """A GRU over the filter's outputs; the correction of the position in units of each track's r."""

    def __init__(self, n_in: int, hidden: int = 128, layers: int = 2):
        super().__init__()
        self.inp = nn.Linear(n_in, hidden)
        self.gru = nn.GRU(hidden, hidden, num_layers=layers, batch_first=True)
        self.out = nn.Linear(hidden, 3)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        h, _ = self.gru(torch.relu(self.inp(feats.to(self.inp.weight.dtype))))
        return self.out(h)


def corrected(state: torch.Tensor, delta: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    out = state.clone()
    out[..., list(POS)] = state[..., list(POS)] + delta.double() * r.double().reshape(-1, 1, 1)
    return out


def average(state: torch.Tensor, batch) -> tuple[float, list[float]]:
    """``immnet evaluate``'s Average RMSE of ``state`` on ``batch`` and its x, y, z (``metrics.rmse``)."""
    truth = batch[keys.STATES]
    score = rmse(position_error(state, truth), scored_mask(truth, batch[keys.MEASUREMENTS]))
    return score["avg"], [score[a] for a in AXES]


def prepared(method, batch):
    state, feats = filter_features(method, batch)
    truth = batch[keys.STATES].double()
    mask = scored_mask(truth, batch[keys.MEASUREMENTS])
    seen = torch.isfinite(batch[keys.MEASUREMENTS]).all(-1)
    return {"state": state, "feats": feats, "truth": torch.nan_to_num(truth[..., list(POS)]), "mask": mask,
            "r": batch[keys.R].double(), "first": seen & (seen.cumsum(1) == 1)}


def deltas_of(model, feats: torch.Tensor, first: torch.Tensor) -> torch.Tensor:
    """The network's corrections ``[B, T, 3]``, none at a track's first detection (reported as the filter reports
    it, as the stage does)."""
    delta = model(feats).double()
    return delta.masked_fill(first.unsqueeze(-1), 0.0)


def loss_of(model, part, idx) -> torch.Tensor:
    """Each window's mean squared error over its scored scans, in units of its r squared, averaged."""
    delta = deltas_of(model, part["feats"][idx], part["first"][idx])
    r = part["r"][idx].reshape(-1, 1, 1)
    pos = part["state"][idx][..., list(POS)] + delta * r
    m = part["mask"][idx].double()
    se = ((pos - part["truth"][idx]) ** 2).sum(-1) / r[..., 0] ** 2 * m
    return (se.sum(1) / m.sum(1).clamp_min(1)).mean()


def predict(model, part, chunk: int = 256) -> torch.Tensor:
    with torch.no_grad():
        deltas = [deltas_of(model, part["feats"][i : i + chunk], part["first"][i : i + chunk])
                  for i in range(0, len(part["feats"]), chunk)]
    return corrected(part["state"], torch.cat(deltas), part["r"])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--train", required=True)
    p.add_argument("--val", required=True)
    p.add_argument("--test", action="append", default=[], help="a test set, scored once at the end (repeatable)")
    p.add_argument("--method", default="real-imm-singer")
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--hidden", type=int, default=128)
    p.add_argument("--views", type=int, default=1, help="fresh views of the training flights per epoch")
    p.add_argument("--turns", type=float, default=0.0,
                   help="the share of training tracks given added turns in each view (FlightAugment(turns=...))")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    torch.manual_seed(args.seed)
    config = load_yaml(method_config(args.method))
    config.setdefault("init_args", {})["return_cov"] = True
    method = instantiate(config)
    train_batch = as_batch(load_dataset(args.train)[0])
    val_batch = as_batch(load_dataset(args.val)[0])
    val = prepared(method, val_batch)
    base_val, _ = average(val["state"], val_batch)
    augment = FlightAugment(seed=args.seed, turns=args.turns)
    model = Residual(val["feats"].shape[-1], hidden=args.hidden)
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    steps = args.epochs * args.views * ((len(train_batch) + args.batch - 1) // args.batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=args.lr, total_steps=steps)
    best, best_state, history = float("inf"), None, []
    print(f"[residual] {args.method} on the validation flights: {base_val:.4f} m", file=sys.stderr, flush=True)
    for epoch in range(args.epochs):
        t0, total, n = time.time(), 0.0, 0
        model.train()
        for v in range(args.views):
            part = prepared(method, augment(train_batch, epoch * args.views + v))
            order = torch.randperm(len(part["feats"]))
            for i in range(0, len(order), args.batch):
                loss = loss_of(model, part, order[i : i + args.batch])
                opt.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(model.parameters(), 1.0)
                opt.step()
                sched.step()
                total, n = total + float(loss.detach()), n + 1
        model.eval()
        score, _ = average(predict(model, val), val_batch)
        history.append({"epoch": epoch, "train_loss": total / n, "val": score})
        if score < best:
            best, best_state = score, {k: v.clone() for k, v in model.state_dict().items()}
        print(f"[residual] epoch {epoch + 1}/{args.epochs}: train {total / n:.4f} r^2, validation {score:.4f} m "
              f"({score / base_val:.4f}x the filter), {time.time() - t0:.0f} s", file=sys.stderr, flush=True)
    model.load_state_dict(best_state)
    model.eval()
    rows = [{"set": args.val, "filter": base_val, "corrected": best}]
    for path in args.test:
        batch = as_batch(load_dataset(path)[0])
        part = prepared(method, batch)
        base, base_axes = average(part["state"], batch)
        score, axes = average(predict(model, part), batch)
        rows.append({"set": path, "filter": base, "corrected": score, "filter_axes": base_axes, "corrected_axes": axes})
    print(f"| set | `{args.method}` [m] | with the learned correction [m] |")
    print("|:---|---:|---:|")
    for row in rows:
        print(f"| {row['set']} | {row['filter']:.3f} | {row['corrected']:.3f} ({row['corrected'] / row['filter']:.3f}x) |")
    if args.json:
        args.json.write_text(json.dumps({"args": vars(args) | {"json": str(args.json)}, "rows": rows,
                                         "history": history}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
