"""The IMM's interaction, mode update and combination (Blom & Bar-Shalom), batched, filters on ``M``.

With mode probabilities ``mu_{t-1}`` ``[B, M]`` and the Markov transition ``Pi[i, j] = P(j at t | i at
t-1)`` (``[M, M]``, or ``[B, M, M]`` per track where a range guard makes it state-dependent):

1. mixing weights ``cbar_j = sum_i Pi_ij mu_i``, ``mu_{i|j} = Pi_ij mu_i / cbar_j``;
2. onset priors: what enters filter ``j`` from filter ``i != j`` (a switch into ``j`` hypothesized)
   has the quantity a switch draws anew replaced by its prior (``onset_priors``: a CA filter's
   acceleration, a turn filter's rate; none for the paper's linear IMMs);
3. mixed estimate ``x0_j = sum_i mu_{i|j} x_{i->j}``, ``P0_j = sum_i mu_{i|j} (P_{i->j} + d d^T)``,
   ``d = x_{i->j} - x0_j``;
4. (after the mode-matched predict and update) the mode update in log space,
   ``mu_j = softmax_j(log cbar_j + l_j)`` (a missed detection gives ``l_j = 0``, so ``mu = cbar``);
5. the combination ``x = sum_j mu_j x_j``, ``P = sum_j mu_j (P_j + (x_j - x)(x_j - x)^T)``.

IMMNet's filter experts (``immnet.stages.filtering``) and every model-based IMM run these functions.
"""

from __future__ import annotations

import math

import torch

from immnet.data.spec import DataSpec
from immnet.motion import ACC, RATE


def transition_matrix(p_stay, M: int, dtype=torch.float64) -> torch.Tensor:
    """``Pi [M, M]`` from ``p_stay`` (``p_stay`` on the diagonal, the rest shared evenly) or a matrix; validated."""
    if isinstance(p_stay, (int, float)):
        if not 0.0 <= p_stay <= 1.0:
            raise ValueError(f"p_stay must be in [0, 1], got {p_stay}")
        off = (1.0 - p_stay) / (M - 1) if M > 1 else 0.0
        Pi = torch.full((M, M), off, dtype=dtype)
        Pi.fill_diagonal_(p_stay if M > 1 else 1.0)
        return Pi
    Pi = torch.as_tensor(p_stay, dtype=dtype)
    if Pi.shape != (M, M):
        raise ValueError(f"transition matrix must be {M}x{M} for {M} models, got shape {tuple(Pi.shape)}")
    if (Pi < 0).any() or not torch.isfinite(Pi).all():
        raise ValueError("transition matrix entries must be finite and non-negative")
    rows = Pi.sum(-1)
    if not torch.allclose(rows, torch.ones_like(rows), atol=1e-9):
        raise ValueError(f"transition matrix rows must sum to 1 (row-stochastic), got row sums {rows.tolist()}")
    return Pi


def onset_priors(own_acc, own_rate, nominal, spec: DataSpec | None = None, n: int = RATE + 1, acc_var=None):
    """What the interaction does to filter ``i``'s posterior entering filter ``j != i``, float64:
    ``keep [M, M, n]`` (1 where a component is kept, 0 where it is replaced), the prior's mean
    ``mean [M, M, n]`` and covariance ``cov [M, M, n, n]`` on the replaced components.

    ``own_acc [M]``: the filters that keep an acceleration of their own (CA: a switch into it draws a new
    one, mean 0 and ``spec.ca_acc_var()``); ``own_rate [M]``: the turn filters that estimate their rate
    (a switch into one draws a rate, ``spec.turn_rate_prior_deg()`` in the sign of ``nominal [M]``); ``n`` the
    state's size (9: no turn rate of its own); ``acc_var`` fixes the acceleration's variances instead."""
    spec = spec or DataSpec()
    M = len(own_acc)
    f64 = torch.float64
    keep = torch.ones(M, M, n, dtype=f64)
    mean, cov = torch.zeros(M, M, n, dtype=f64), torch.zeros(M, M, n, n, dtype=f64)
    w_mean, w_std = (v * math.pi / 180.0 for v in spec.turn_rate_prior_deg())
    for j in range(M):
        others = [i for i in range(M) if i != j]
        if own_acc[j]:
            for a, v in zip(ACC, spec.ca_acc_var() if acc_var is None else acc_var):
                keep[others, j, a] = 0.0
                cov[others, j, a, a] = v
        if own_rate[j]:
            keep[others, j, RATE] = 0.0
            mean[others, j, RATE] = math.copysign(w_mean, nominal[j])
            cov[others, j, RATE, RATE] = w_std**2
    return keep, mean, cov


def mixing_weights(mu: torch.Tensor, Pi: torch.Tensor) -> torch.Tensor:
    """``mu_{i|j} = Pi_ij mu_i / sum_k Pi_kj mu_k``, ``[B, i, j]``, from ``mu [B, M]`` and ``Pi`` ``[M, M]``
    or ``[B, M, M]``."""
    joint = mu.unsqueeze(-1) * Pi
    return joint / joint.sum(-2, keepdim=True)


def entering(x: torch.Tensor, P: torch.Tensor, keep: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor):
    """What each filter ``i``'s posterior (``x [B, i, n]``, ``P [B, i, n, n]``) brings into each filter ``j``:
    ``x_{i->j} [B, i, j, n]``, ``P_{i->j} [B, i, j, n, n]``, with ``onset_priors``' ``keep, mean, cov``."""
    keep, mean, cov = keep.to(x.dtype), mean.to(x.dtype), cov.to(x.dtype)
    xc = x.unsqueeze(2) * keep + mean
    Pc = P.unsqueeze(2) * (keep.unsqueeze(-1) * keep.unsqueeze(-2)) + cov
    return xc, Pc


def mix(w: torch.Tensor, xc: torch.Tensor, Pc: torch.Tensor):
    """The mixed estimate of each filter ``x0 [B, j, n]``, ``P0 [B, j, n, n]`` from the mixing weights
    ``w [B, i, j]`` and the entering estimates ``xc [B, i, j, n]``, ``Pc [B, i, j, n, n]`` (or ``[B, i, n]``
    and ``[B, i, n, n]``, the same for every ``j``: no onset priors)."""
    if xc.dim() == w.dim():
        xc, Pc = xc.unsqueeze(2), Pc.unsqueeze(2)
    x0 = (w.unsqueeze(-1) * xc).sum(1)
    d = xc - x0.unsqueeze(1)
    P0 = (w[..., None, None] * (Pc + d.unsqueeze(-1) * d.unsqueeze(-2))).sum(1)
    return x0, P0


def mode_update(prior_log: torch.Tensor, loglik: torch.Tensor) -> torch.Tensor:
    """``mu_j = softmax_j(log cbar_j + l_j)``: the posterior mode probabilities ``[B, M]`` from the predicted
    ones' logarithm and the filters' innovation log-likelihoods (0 where the detection is missed)."""
    return torch.softmax(prior_log + loglik, -1)


def combine(x: torch.Tensor, P: torch.Tensor | None, mu: torch.Tensor):
    """Moment-matched fusion ``x = sum mu_j x_j`` (``x [B, M, n]``) and, where ``P`` is given,
    ``P = sum mu_j (P_j + d_j d_j^T)``; returns ``(x, P or None)``."""
    xf = (mu.unsqueeze(-2) @ x).squeeze(-2)
    if P is None:
        return xf, None
    d = x - xf.unsqueeze(-2)
    Pf = torch.einsum("bm,bmij->bij", mu, P) + (mu.unsqueeze(-1) * d).transpose(-1, -2) @ d
    return xf, Pf
