"""The IMM's interaction, mode update and combination (Blom & Bar-Shalom), batched, filters on ``M``.

With mode probabilities ``mu_{t-1}`` ``[B, M]`` and the Markov transition ``Pi[i, j] = P(j at t | i at
t-1)`` (``[M, M]``, or ``[B, M, M]`` per track where a range guard makes it state-dependent):

1. mixing weights ``cbar_j = sum_i Pi_ij mu_i``, ``mu_{i|j} = Pi_ij mu_i / cbar_j``;
2. onset priors: what enters filter ``j`` from filter ``i != j`` (a switch into ``j`` hypothesized)
   has the quantity a switch draws anew replaced by its prior (``onset_priors``: a CA filter's
   acceleration, a turn filter's rate; none for the paper's linear IMMs);
3. mixed estimate ``x0_j = sum_i mu_{i|j} x_{i->j}``, ``P0_j = sum_i mu_{i|j} (P_{i->j} + d d^T)``,
   ``d = x_{i->j} - x0_j``, as products over ``i`` (``mix``: the ``[B, i, j, n, n]`` entering
   covariances are never formed);
4. (after the mode-matched predict and update) the mode update in log space,
   ``mu_j = softmax_j(log cbar_j + l_j)`` (a missed detection gives ``l_j = 0``, so ``mu = cbar``);
5. the combination ``x = sum_j mu_j x_j``, ``P = sum_j mu_j (P_j + (x_j - x)(x_j - x)^T)``.

IMMNet's filter experts (``immnet.stages.filtering``) and every model-based IMM run these functions.
"""

from __future__ import annotations

import math

import torch

from immnet.motion import ACC, RATE

ONSET_ACC_VAR = ((3.0**3 - 0.5**3) / (3.0 * (3.0 - 0.5)) / 2.0,) * 2 + (0.3**2 / 3.0,)
"""The default variance per axis (x, y, z) of the acceleration a switch into a CA filter draws: 3D-LAST's, a
horizontal magnitude ``U[0.5, 3]`` m/s^2 at a uniform direction and a vertical ``U[-0.3, 0.3]`` (1.7917, 1.7917,
0.03; ``immnet.data.spec.DataSpec.ca_acc_var`` of another data set's)."""
ONSET_RATE_PRIOR_DEG = ((1.0 + 10.0) / 2.0, (10.0 - 1.0) / 12.0**0.5)
"""The default mean and standard deviation (deg/s) of the rate a switch into a turn filter draws: 3D-LAST's
magnitude ``U[1, 10]`` (5.5 and 2.6; ``DataSpec.turn_rate_prior_deg`` of another data set's)."""


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


def onset_priors(own_acc, own_rate, nominal, n: int = RATE + 1, acc_var=None, rate_prior_deg=None):
    """What enters filter ``j`` from any other filter (a switch into ``j``), float64: ``keep [M, n]`` (1
    where a component is kept, 0 where it is replaced), the prior's mean ``mean [M, n]`` and covariance
    ``cov [M, n, n]`` on the replaced components. What a filter brings into itself is kept whole.

    ``own_acc [M]``: the filters that keep an acceleration of their own (CA: a switch into it draws a new
    one, mean 0 and variances ``acc_var``, None: ``ONSET_ACC_VAR``); ``own_rate [M]``: the turn filters that
    estimate their rate (a switch into one draws a rate, ``rate_prior_deg`` ``(mean, std)``, None:
    ``ONSET_RATE_PRIOR_DEG``, in the sign of ``nominal [M]``); ``n`` the state's size (9: no turn rate of its own)."""
    M = len(own_acc)
    f64 = torch.float64
    keep = torch.ones(M, n, dtype=f64)
    mean, cov = torch.zeros(M, n, dtype=f64), torch.zeros(M, n, n, dtype=f64)
    w_mean, w_std = (v * math.pi / 180.0 for v in (rate_prior_deg or ONSET_RATE_PRIOR_DEG))
    for j in range(M):
        if own_acc[j]:
            for a, v in zip(ACC, ONSET_ACC_VAR if acc_var is None else acc_var):
                keep[j, a] = 0.0
                cov[j, a, a] = v
        if own_rate[j]:
            keep[j, RATE] = 0.0
            mean[j, RATE] = math.copysign(w_mean, nominal[j])
            cov[j, RATE, RATE] = w_std**2
    return keep, mean, cov


def enter(x: torch.Tensor, P: torch.Tensor, keep: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor):
    """One posterior ``x [..., n]``, ``P [..., n, n]`` entering a filter it is not, with that filter's onset
    prior (a row of ``onset_priors``: ``keep [..., n]``, ``mean [..., n]``, ``cov [..., n, n]``):
    ``keep x + mean`` and ``(keep keep^T) P + cov``; the prior taken to ``x``'s dtype and device."""
    keep, mean, cov = keep.to(x), mean.to(x), cov.to(x)
    return x * keep + mean, P * (keep[..., :, None] * keep[..., None, :]) + cov


def mixing_weights(mu: torch.Tensor, Pi: torch.Tensor) -> torch.Tensor:
    """``mu_{i|j} = Pi_ij mu_i / sum_k Pi_kj mu_k``, ``[B, i, j]``, from ``mu [B, M]`` and ``Pi`` ``[M, M]``
    or ``[B, M, M]``. Where nothing can enter ``j`` (``cbar_j = 0``: a transition matrix with zeros, ``p_stay`` 1,
    once ``mu`` of every mode that reaches ``j`` has underflowed to 0) the weights are 0, not ``0 / 0``: the filter
    restarts from nothing and its mode keeps probability 0."""
    joint = mu.unsqueeze(-1) * Pi
    return joint / joint.sum(-2, keepdim=True).clamp_min(torch.finfo(joint.dtype).tiny)


def entering(x: torch.Tensor, keep: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
    """The mean each filter ``i`` (``x [B, i, n]``) brings into each filter ``j``, ``x_{i->j} [B, i, j, n]``:
    ``x_i`` itself for ``i = j``, ``keep_j x_i + mean_j`` from ``i != j`` (``onset_priors``' ``keep, mean``)."""
    M = x.shape[-2]
    own = torch.eye(M, dtype=torch.bool, device=x.device)[..., None]
    xi = x.unsqueeze(2)
    return torch.where(own, xi, xi * keep.to(x.dtype) + mean.to(x.dtype))


def _weighted(W: torch.Tensor, P: torch.Tensor, mask=None, cov=None) -> torch.Tensor:
    """``sum_i W_ij P_{i->j}`` ``[B, j, r, n]`` of the entering covariances (rows ``r`` of them): ``P_i``
    (``P [B, i, r, n]``) from ``i = j``, ``mask_j * P_i + cov_j`` (``[j, r, n]``) from ``i != j``; one
    product over ``i``, no ``[B, i, j, n, n]`` tensor."""
    if mask is None:
        return torch.einsum("bij,birn->bjrn", W, P)
    M = W.shape[-1]
    own = torch.diagonal(W, 0, -2, -1)  # W_jj [B, j]
    off = W.masked_fill(torch.eye(M, dtype=torch.bool, device=W.device), 0.0)
    return own[..., None, None] * P + mask * torch.einsum("bij,birn->bjrn", off, P) + off.sum(1)[..., None, None] * cov


def _spread(W: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """``sum_i W_ij d_ij d_ij^T`` ``[B, j, n, n]`` from ``W [B, i, j]`` and ``d [B, i, j, n]``."""
    return (W.unsqueeze(-1) * d).permute(0, 2, 3, 1) @ d.transpose(1, 2)


def mix(w: torch.Tensor, x: torch.Tensor, P: torch.Tensor, priors=None, bound=None):
    """The mixed estimate of each filter ``x0 [B, j, n]``, ``P0 [B, j, n, n]`` from the mixing weights
    ``w [B, i, j]`` and the filters' posteriors ``x [B, i, n]``, ``P [B, i, n, n]``:
    ``x0_j = sum_i w_ij x_{i->j}``, ``P0_j = sum_i w_ij (P_{i->j} + d d^T)``, ``d = x_{i->j} - x0_j``.

    ``priors``: ``onset_priors``' ``(keep, mean, cov)``, what enters ``j`` from another filter,
    ``x_{i->j} = keep_j x_i + mean_j``, ``P_{i->j} = (keep_j keep_j^T) P_i + cov_j`` (None: every
    filter enters whole). ``bound``: ``(share [B, i, j], rate [j], var, index)``, a range guard's
    bound turn: a ``share`` of each entry is a second mixture component, the entry with its component
    ``index`` replaced by ``N(rate_j, var)`` (its cross-covariances 0). The sums over ``i`` are products
    (``_weighted``, ``_spread``): nothing of size ``[B, i, j, n, n]`` is formed."""
    if priors is None:
        xc, mask, cov = x.unsqueeze(2).expand(*w.shape, x.shape[-1]), None, None
    else:
        keep, mean, cov = (v.to(x) for v in priors)  # onset_priors' are float64 on the CPU
        xc, mask = entering(x, keep, mean), keep[:, :, None] * keep[:, None, :]
    if bound is None:
        x0 = (w.unsqueeze(-1) * xc).sum(1)
        return x0, _weighted(w, P, mask, cov) + _spread(w, xc - x0.unsqueeze(1))
    share, rate, var, index = bound
    a = share.to(x.dtype)
    wb = w * a  # the bound components' weights; the scheduled ones' are w (1 - a)
    ws = w * (1 - a)
    at = torch.arange(x.shape[-1], device=x.device) == index
    rate = rate.to(x.dtype)[:, None]  # [j, 1]
    xb = torch.where(at, rate, xc)  # the bound components' means
    x0 = (w.unsqueeze(-1) * torch.where(at, (1 - a).unsqueeze(-1) * xc + a.unsqueeze(-1) * rate, xc)).sum(1)
    x0_ = x0.unsqueeze(1)
    spread = _spread(torch.cat([ws, wb], 1), torch.cat([xc - x0_, xb - x0_], 1))
    # the bound components zero the rows and columns ``index`` of what they bring: those of the sum are the
    # scheduled components' alone, plus the bound rate's variance
    row = _weighted(ws, P[..., index:index + 1, :], None if mask is None else mask[:, index:index + 1],
                    None if cov is None else cov[:, index:index + 1])
    row = row + (wb.sum(1) * var)[..., None, None] * at.to(x.dtype)
    P0 = _weighted(w, P, mask, cov)
    P0 = torch.where(at[:, None], row, torch.where(at, row.transpose(-1, -2), P0))
    return x0, P0 + spread


def mode_update(prior_log: torch.Tensor, loglik: torch.Tensor) -> torch.Tensor:
    """``mu_j = softmax_j(log cbar_j + l_j)``: the posterior mode probabilities ``[B, M]`` from the predicted
    ones' logarithm and the filters' innovation log-likelihoods (0 where the detection is missed)."""
    return torch.softmax(prior_log + loglik, -1)


def moment_match(weights: torch.Tensor, x: torch.Tensor, xf: torch.Tensor, P: torch.Tensor) -> torch.Tensor:
    """The covariance of a Gaussian mixture about its mean, ``sum_j W_j (P_j + d_j d_j^T)``, ``d_j = x_j - xf``: the
    components' means ``x [B, M, n]`` and covariances ``P [B, M, n, n]``, the mean ``xf [B, n]``, weights ``W``
    broadcastable to ``[B, M, n, n]`` (``mu [B, M, 1, 1]``; modes per group weigh each block with its group's
    probability, ``immnet.stages.base.block_weights``); in ``P``'s dtype."""
    d = (x - xf.unsqueeze(-2)).to(P.dtype)
    return (weights.to(P.dtype) * (P + d.unsqueeze(-1) * d.unsqueeze(-2))).sum(-3)


def combine(x: torch.Tensor, P: torch.Tensor | None, mu: torch.Tensor):
    """Moment-matched fusion ``x = sum mu_j x_j`` (``x [B, M, n]``) and, where ``P`` is given, its covariance
    ``moment_match``; returns ``(x, P or None)``."""
    xf = (mu.unsqueeze(-2) @ x).squeeze(-2)
    return xf, None if P is None else moment_match(mu[..., None, None], x, xf, P)
