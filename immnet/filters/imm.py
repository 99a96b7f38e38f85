"""The interacting multiple model filter (Blom & Bar-Shalom), batched, experts stacked on ``M``.

One step, in the order of FilterPy's ``IMMEstimator`` (``predict`` then ``update``), with mode
probabilities ``mu_{t-1}`` ``[B, M]`` and the Markov transition ``Pi[i, j] = P(j at t | i at t-1)``:

1. mixing: ``cbar_j = sum_i Pi_ij mu_i``, ``w_ij = Pi_ij mu_i / cbar_j``,
   ``x0_j = sum_i w_ij x_i``, ``P0_j = sum_i w_ij (P_i + (x_i - x0_j)(x_i - x0_j)^T)``;
2. mode-matched prediction: ``x_j = F_j x0_j``, ``P_j = F_j P0_j F_j^T + Q_j``;
3. mode-matched update with ``z_t`` (``immnet.filters.kalman.update``), log-likelihoods ``l_j``;
4. mode update in log space: ``log mu_j = log cbar_j + l_j - logsumexp_k(log cbar_k + l_k)``
   (a missed detection gives ``l_j = 0``, so ``mu = cbar``);
5. combination: ``x = sum_j mu_j x_j`` (and ``P = sum_j mu_j (P_j + (x_j - x)(x_j - x)^T)``).

Everything is one batched tensor expression per stage: no loop over tracks or experts.
"""

from __future__ import annotations

import torch

from immnet.filters.kalman import update

VEL_STD = 300.0
"""Initial velocity standard deviation (m/s), every axis: covers the 340 m/s speed bound."""
ACC_STD = 10.0
"""Initial acceleration standard deviation (m/s^2), every axis."""


def initial_state(z: torch.Tensor, r, vel_std: float = VEL_STD, acc_std: float = ACC_STD):
    """``x0``, ``P0`` from the first measurement of each track (SPEC.md section 3).

    ``z [B, T, 3]``; ``r`` the filter's assumed measurement standard deviation (scalar or ``[B]``).
    ``x0 = [z0x, 0, 0, z0y, 0, 0, z0z, 0, 0]`` and ``P0 = diag(r^2, vel_std^2, acc_std^2)`` per axis.
    A track whose first measurement is missing starts at its first detected position (zeros if it
    has none), the one place where an estimate looks ahead.
    """
    finite = ~torch.isnan(z).any(-1)  # [B, T]
    first = torch.where(finite.any(-1), finite.long().argmax(-1), torch.zeros_like(finite[:, 0], dtype=torch.long))
    z0 = z.gather(1, first[:, None, None].expand(-1, 1, 3))[:, 0]
    z0 = torch.nan_to_num(z0, nan=0.0)
    B = z.shape[0]
    x0 = z.new_zeros(B, 9)
    x0[:, 0::3] = z0
    r2 = torch.as_tensor(r, dtype=z.dtype, device=z.device) ** 2
    diag = z.new_zeros(B, 9)
    diag[:, 0::3] = r2.reshape(-1, 1) if r2.dim() else r2
    diag[:, 1::3] = vel_std**2
    diag[:, 2::3] = acc_std**2
    return x0, torch.diag_embed(diag)


def mix(x, P, mu, Pi):
    """Mixing stage: ``x [B, M, n]``, ``P [B, M, n, n]``, ``mu [B, M]``, ``Pi [M, M]`` -> ``x0, P0, cbar``."""
    cbar = mu @ Pi  # [B, M]
    w = Pi * mu[..., :, None] / cbar.clamp_min(torch.finfo(mu.dtype).tiny)[..., None, :]  # [B, i, j]
    wt = w.transpose(-1, -2)  # [B, j, i]
    x0 = wt @ x  # [B, j, n]
    d = x.unsqueeze(-3) - x0.unsqueeze(-2)  # [B, j, i, n]: x_i - x0_j
    wd = wt.unsqueeze(-1) * d
    P0 = torch.einsum("bji,bimn->bjmn", wt, P) + wd.transpose(-1, -2) @ d
    return x0, P0, cbar


def combine(x, P, mu):
    """Moment-matched fusion ``x = sum mu_j x_j``, ``P = sum mu_j (P_j + d_j d_j^T)``."""
    xf = (mu.unsqueeze(-2) @ x).squeeze(-2)
    d = x - xf.unsqueeze(-2)
    Pf = torch.einsum("bm,bmij->bij", mu, P) + (mu.unsqueeze(-1) * d).transpose(-1, -2) @ d
    return xf, Pf


def imm_step(x, P, mu, z, F, Ft, Q, R, Pi):
    """One IMM cycle: ``x [B, M, 9]``, ``P [B, M, 9, 9]``, ``mu [B, M]``, ``z [B, 3]`` (NaN = missed).

    ``F``, ``Ft = F^T`` and ``Q`` broadcast to ``[B, M, 9, 9]``; ``R`` broadcasts to ``[B, M, 3, 3]``
    (e.g. ``r^2 I`` as ``[B, 1, 3, 3]`` or a scalar variance). Returns ``x, P, mu, x_fused``.
    """
    x0, P0, cbar = mix(x, P, mu, Pi)
    x = (F @ x0.unsqueeze(-1)).squeeze(-1)
    P = F @ P0 @ Ft + Q
    x, P, ll = update(x, P, z.unsqueeze(-2), None, R)
    logp = torch.log(cbar) + ll
    mu = torch.softmax(logp, dim=-1)
    xf = (mu.unsqueeze(-2) @ x).squeeze(-2)
    return x, P, mu, xf


def imm_filter(z, x0, P0, F, Q, R, Pi, mu0, return_experts: bool = False, step=imm_step):
    """Run the IMM over ``z [B, T, 3]`` from ``x0 [B, 9]``, ``P0 [B, 9, 9]`` and ``mu0 [M]``.

    At ``t = 0`` the output is the initial state (every expert at ``x0, P0``); steps ``t >= 1``
    filter ``z_t``. Returns ``state [B, T, 9]``, ``probs [B, T, M]`` and, with ``return_experts``,
    the experts' posteriors ``[B, T, M, 9]`` (else None).
    """
    B, T, _ = z.shape
    M = Pi.shape[-1]
    x = x0.unsqueeze(1).expand(B, M, 9).contiguous()
    P = P0.unsqueeze(1).expand(B, M, 9, 9).contiguous()
    mu = mu0.to(z).expand(B, M).contiguous()
    Ft = F.transpose(-1, -2).contiguous()
    states = z.new_empty(B, T, 9)
    probs = z.new_empty(B, T, M)
    experts = z.new_empty(B, T, M, 9) if return_experts else None
    states[:, 0], probs[:, 0] = x0, mu
    if return_experts:
        experts[:, 0] = x
    for t in range(1, T):
        x, P, mu, xf = step(x, P, mu, z[:, t], F, Ft, Q, R, Pi)
        states[:, t], probs[:, t] = xf, mu
        if return_experts:
            experts[:, t] = x
    return states, probs, experts
