"""Would a learned per-scan scale make an output-corrected network's reported covariance honest in the core?

A network with an output correction reports its filters' covariance for the corrected estimate, a little wide in the
core (its 50 % ellipsoid holds about 0.55 of the truth) and right at 95 % (docs/real.md "Calibration"). This fits,
on a fresh view of the training flights, a scale of the reported position covariance per axis, ``D P D`` with
``D = diag(exp(s / 2))``, by the Gaussian likelihood of the corrected estimate's error, two ways:

- a constant ``s`` per axis;
- ``s_t = W h_t + b`` from the correction's GRU states after scan ``t`` (each member's last layer, standardized on
  the training view): what the network's own memory of the track says of how far off its estimate is now, the
  input a learned variance beside the correction would have. The ridge weight is chosen by the validation likelihood.

Then the coverage of each one's ellipsoids on the validation flights (and ``--test`` sets), from scan 20 on as
``scripts/calibration.py`` scores them. A study, not a tracker: nothing here changes what a network reports.

    python scripts/covariance_scale.py --checkpoint immnet/pretrained/immnet-real.ckpt \\
        --train runs/real/data/quickstart-1s/train --val runs/real/data/quickstart-1s/val
"""

from __future__ import annotations

import argparse
import sys
import time

import torch

from immnet import keys
from immnet.data.augment import FlightAugment
from immnet.data.storage import as_batch, load_dataset
from immnet.evaluation.calibration import LEVELS, coverage
from immnet.evaluation.metrics import scored_mask
from immnet.motion import POS
from immnet.stages.correct import CorrectionEnsemble, OutputCorrection
from immnet.tracking.methods import IMMNetMethod

RIDGE = (1e-2, 1e-3, 1e-4)
VIEW_STEP = 10**6  # a view of the training flights that no training step drew


def collect(method, batch, from_scan: int = 20, chunk: int = 256):
    """The correction's GRU states ``[S, F]``, the reported position's error ``[S, 3]`` and covariance ``[S, 3, 3]``
    (float64) of the scans ``S`` scored from ``from_scan`` on."""
    stage = next((m for m in method.net.modules() if isinstance(m, (CorrectionEnsemble, OutputCorrection))), None)
    if stage is None:
        raise ValueError(f"{method.name} has no output correction: nothing to read a per-scan scale from")
    states = []

    def keep(module, args, td):
        h = td.get(keys.OUTPUT_HIDDEN)  # [B, layers, hidden] or [B, K, layers, hidden]
        states.append(h[..., -1, :].reshape(h.shape[0], -1).clone())

    handle = stage.register_forward_hook(keep)
    feats, errs, covs = [], [], []
    pos = list(POS)
    try:
        for i in range(0, len(batch), chunk):
            part = batch[i : i + chunk]
            states.clear()
            with torch.no_grad():
                out = method.track(part)
            T = part[keys.MEASUREMENTS].shape[1]
            if len(states) != T:
                raise RuntimeError(f"the correction ran {len(states)} times over {T} scans (coasted scans?)")
            truth = part[keys.STATES].double()
            e = out[keys.STATE][..., pos] - truth[..., pos]
            P = out[keys.STATE_COV][..., pos, :][..., pos]
            mask = scored_mask(truth, part[keys.MEASUREMENTS])
            mask[:, :from_scan] = False
            mask &= torch.isfinite(e).all(-1) & torch.isfinite(P).flatten(-2).all(-1)
            feats.append(torch.stack(states, 1)[mask].double())
            errs.append(e[mask])
            covs.append(P[mask])
    finally:
        handle.remove()
    return torch.cat(feats), torch.cat(errs), torch.cat(covs)


def scaled_nees(e: torch.Tensor, P: torch.Tensor, s: torch.Tensor | None = None) -> torch.Tensor:
    """``e^T (D P D)^{-1} e`` ``[S]`` with ``D = diag(exp(s / 2))`` (``s [S, 3]`` or ``[3]``; None: ``D = I``)."""
    if s is not None:
        e = e * torch.exp(-s / 2)
    return (e * torch.linalg.solve(P, e.unsqueeze(-1)).squeeze(-1)).sum(-1)


def nll(e, P_inv, s) -> torch.Tensor:
    """The mean negative Gaussian log-likelihood of the errors ``e`` under ``D P D`` (``P_inv``: ``P``'s inverse),
    less what does not depend on ``s``."""
    ed = e * torch.exp(-s / 2)
    return (0.5 * (ed * (P_inv @ ed.unsqueeze(-1)).squeeze(-1)).sum(-1) + 0.5 * s.expand_as(e).sum(-1)).mean()


class Scale:
    """``s = W ((h - mean) / std) + b``; ``W`` None: a constant ``s = b`` per axis."""

    def __init__(self, b, W=None, mean=None, std=None):
        self.b, self.W, self.mean, self.std = b, W, mean, std

    def __call__(self, h: torch.Tensor | None) -> torch.Tensor:
        if self.W is None:
            return self.b if h is None else self.b.expand(h.shape[0], 3)
        return ((h - self.mean) / self.std) @ self.W + self.b


def fit(h, e, P, ridge: float | None = None, max_iter: int = 300) -> Scale:
    """The scale of the errors ``e`` under ``P`` by maximum likelihood (L-BFGS): constant per axis where ``ridge`` is
    None, else from the states ``h`` with an L2 penalty ``ridge * |W|^2``."""
    b = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    if ridge is None:
        W = mean = std = None
        params = [b]
    else:
        mean, std = h.mean(0), h.std(0).clamp_min(1e-6)
        W = torch.zeros(h.shape[1], 3, dtype=torch.float64, requires_grad=True)
        params = [W, b]
    scale, P_inv = Scale(b, W, mean, std), torch.linalg.inv(P)
    opt = torch.optim.LBFGS(params, max_iter=max_iter, tolerance_grad=1e-10, tolerance_change=1e-14,
                            line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = nll(e, P_inv, scale(h)) + (0.0 if W is None else ridge * (W**2).sum())
        loss.backward()
        return loss

    opt.step(closure)
    return Scale(b.detach(), None if W is None else W.detach(), mean, std)


def row(name: str, e, P, s=None) -> str:
    nees = scaled_nees(e, P, s)
    cells = " | ".join(f"{v:.3f}" for v in coverage(nees, torch.ones_like(nees, dtype=torch.bool)).values())
    return f"| {name} | {cells} | {float(nees.mean()):.2f} |"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", required=True, help="a network with an output correction (one or an ensemble)")
    p.add_argument("--train", required=True, help="its training flights: a fresh view of them fits the scales")
    p.add_argument("--val", required=True, help="chooses the ridge weight; its coverage is printed")
    p.add_argument("--test", action="append", default=[], help="a set scored once at the end (repeatable)")
    p.add_argument("--from-scan", type=int, default=20)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    torch.manual_seed(args.seed)
    method = IMMNetMethod(args.checkpoint, name="network", return_cov=True)
    t0 = time.time()

    def sets(path, view=None):
        batch = as_batch(load_dataset(path)[0])
        batch = batch if view is None else FlightAugment(seed=args.seed)(batch, view)
        out = collect(method, batch, args.from_scan)
        print(f"[scale] {path}: {len(out[0])} scans, {time.time() - t0:.0f} s", file=sys.stderr, flush=True)
        return out

    h, e, P = sets(args.train, VIEW_STEP)
    hv, ev, Pv = sets(args.val)
    const = fit(h, e, P)
    heads = {}
    for w in RIDGE:
        heads[w] = fit(h, e, P, w)
        print(f"[scale] per-scan scale fitted, ridge {w:g}: {time.time() - t0:.0f} s", file=sys.stderr, flush=True)
    Pv_inv = torch.linalg.inv(Pv)
    ridge = min(RIDGE, key=lambda w: float(nll(ev, Pv_inv, heads[w](hv))))
    head = heads[ridge]
    print(f"[scale] constant scale of the variance per axis {[round(float(v), 3) for v in torch.exp(const.b)]}; "
          f"per-scan head: ridge {ridge:g} (validation likelihood)", file=sys.stderr)
    levels = " | ".join(f"{p:.0%}" for p in LEVELS)
    print(f"| set, covariance | {levels} | mean NEES (3) |")
    print("|:---|" + "---:|" * (len(LEVELS) + 1))
    for path, (hs, es, Ps) in [(args.val, (hv, ev, Pv))] + [(t, sets(t)) for t in args.test]:
        print(row(f"{path}: as reported", es, Ps))
        print(row("a constant scale per axis", es, Ps, const(hs)))
        print(row("a per-scan scale from the GRU states", es, Ps, head(hs)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
