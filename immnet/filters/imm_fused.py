"""The IMM step for shared ``F``, ``Q`` written for ``torch.compile``: batch last, small sums unrolled.

Opt-in through ``imm_filter(..., compile=True)``. Every tensor keeps the tracks on its last dimension
(``x [M, 9, B]``, ``P [M, 9, 9, B]``, ``mu [M, B]``) and every contraction over a small dimension (the
``M`` experts, the 9 states, the 3 positions) is written as a sum of broadcast products, so that
inductor turns the whole step into a few vectorized loops over the tracks (one pass each for the mixed
``P0``, ``F P0``, and the posterior ``P``) instead of one kernel per op. The equations are those of
``immnet.filters.imm`` (Blom & Bar-Shalom, FilterPy's order):

- mixing ``cbar_j = sum_i Pi_ij mu_i``, ``w_ji = Pi_ij mu_i / cbar_j``, ``x0_j = sum_i w_ji x_i``,
  ``P0_j = sum_i w_ji (P_i + (x_i - x0_j)(x_i - x0_j)^T)``;
- prediction ``x_j = F_j x0_j``, ``P_j = F_j sym(P0_j) F_j^T + Q_j`` (``sym(A) = (A + A^T) / 2``, which
  keeps float32 covariances symmetric, as the eager paths do), of which the update needs
  ``P_j H^T`` (the position columns 0, 3, 6) before it needs the rest;
- update ``S = H P H^T + R`` inverted by its adjugate, ``K = P H^T S^-1``, ``x += K y``,
  ``P -= K (P H^T)^T``, ``l_j = -(y^T S^-1 y + log det S) / 2`` (the ``-3/2 log 2 pi`` cancels);
- ``mu_j = softmax_j(log cbar_j + l_j)``, ``x = sum_j mu_j x_j``.

A missed detection (NaN in ``z``) zeroes the innovation, the gain and the likelihood: predict only.
Eager, this formulation is slow (hundreds of small ops); it exists to be compiled.
"""

from __future__ import annotations

import logging

import torch

log = logging.getLogger(__name__)


def _dot(a, b, dim: int):
    """``sum_k a_k b_k`` over a small (negative) ``dim``, broadcasting: one product per term."""
    n = max(a.shape[dim], b.shape[dim])
    at = lambda t, k: t.select(dim, k if t.shape[dim] > 1 else 0)  # noqa: E731
    out = at(a, 0) * at(b, 0)
    for k in range(1, n):
        out = out + at(a, k) * at(b, k)
    return out


def fused_step(x, P, mu, z, miss, F, Q, PiT, R):
    """One IMM cycle, tracks last: ``x [M, 9, B]``, ``P [M, 9, 9, B]``, ``mu [M, B]``, ``z [3, B]``,
    ``miss [B]`` (bool), ``F [M, 9, 9, 1]``, ``Q [M, 9, 9, 1]``, ``PiT = Pi^T [M, M, 1]``, ``R [3, 3, 1]``.

    Returns ``x, P, mu`` of the experts and the fused state ``[9, B]``.
    """
    M = PiT.shape[0]
    cbar = _dot(PiT, mu, -2)  # [j, B]
    w = PiT * (mu * cbar.clamp_min(torch.finfo(cbar.dtype).tiny).reciprocal()[:, None])  # [j, i, B]; 0 where cbar 0
    xm = _dot(w[:, :, None], x, -3)  # [j, 9, B]
    Pm = None
    for i in range(M):  # P0_j = sum_i w_ji (P_i + d d^T), d = x_i - x0_j
        d = x[i] - xm
        term = w[:, i, None, None] * (P[i] + d[:, :, None] * d[:, None, :])
        Pm = term if Pm is None else Pm + term
    xp = _dot(F, xm[:, None], -2)  # [M, 9, B]
    Pm = 0.5 * (Pm + Pm.transpose(1, 2))  # symmetrize once per step (read inline by the next line)
    A = _dot(F[:, :, :, None], Pm[:, None], -3)  # (F P0)[l, c] = sum_r F[l, r] P0[r, c]
    PHt = _dot(A[:, :, None], F[:, None, 0::3], -2) + Q[:, :, 0::3]  # [M, 9, 3, B]
    S = PHt[:, 0::3] + R
    s00, s01, s02, s11, s12, s22 = S[:, 0, 0], S[:, 0, 1], S[:, 0, 2], S[:, 1, 1], S[:, 1, 2], S[:, 2, 2]
    c00, c01, c02 = s11 * s22 - s12 * s12, s02 * s12 - s01 * s22, s01 * s12 - s02 * s11
    c11, c12, c22 = s00 * s22 - s02 * s02, s01 * s02 - s00 * s12, s00 * s11 - s01 * s01
    det = s00 * c00 + s01 * c01 + s02 * c02
    Si = torch.stack([torch.stack(r, 1) for r in ((c00, c01, c02), (c01, c11, c12), (c02, c12, c22))], 1)
    Si = Si * det.reciprocal()[:, None, None]  # [M, 3, 3, B], symmetric
    y = torch.where(miss, 0.0, z - xp[:, 0::3])  # [M, 3, B]
    Siy = _dot(Si, y[:, None], -2)
    x = xp + _dot(PHt, Siy[:, None], -2)
    K = torch.where(miss, 0.0, _dot(PHt[:, :, :, None], Si[:, None], -3))  # [M, 9, 3, B]
    P = _dot(A[:, :, None], F[:, None], -2) + Q - _dot(K[:, :, None], PHt[:, None], -2)
    ll = torch.where(miss, 0.0, -0.5 * (_dot(y, Siy, -2) + det.log()))
    mu = torch.softmax(cbar.log() + ll, 0)
    return x, P, mu, _dot(mu[:, None], x, -3)


_compiled = None
_broken = False


def compiled_step():
    """``torch.compile(fused_step)`` (built once; dynamo keeps one graph per dtype, device and M)."""
    global _compiled
    if _compiled is None:
        _compiled = torch.compile(fused_step, fullgraph=True)
    return _compiled


def imm_filter_fused(z, x0, P0, F, Q, R, Pi, mu0, return_experts: bool, step=None, start=None):
    """``imm_filter`` for shared ``F``, ``Q`` ``[M, 9, 9]`` with the compiled ``fused_step``.

    Returns None (and logs why) if compiling fails, e.g. without a C++ compiler; the caller then
    runs the eager path. ``step`` replaces the compiled step (tests run ``fused_step`` eagerly). ``start [B]``: the
    scan at which each track starts from ``x0``, ``P0`` (``runner.run``'s).
    """
    global _broken
    from immnet.imm.kalman import _as_cov
    from immnet.imm.runner import late_starts

    if step is None:
        if _broken:
            return None
        step = compiled_step()
    B, T, _ = z.shape
    M = Pi.shape[-1]
    zz = z.permute(1, 2, 0).contiguous()  # [T, 3, B]
    miss = torch.isnan(zz).any(1)  # [T, B]
    x = x0.T.unsqueeze(0).expand(M, 9, B).contiguous()
    P = P0.permute(1, 2, 0).unsqueeze(0).expand(M, 9, 9, B).contiguous()
    mu = mu0.to(z)[:, None].expand(M, B).contiguous()
    consts = (
        F.unsqueeze(-1).contiguous(), Q.expand(M, 9, 9).unsqueeze(-1).contiguous(),
        Pi.T.unsqueeze(-1).contiguous(), _as_cov(R, 3, z).unsqueeze(-1).contiguous(),
    )
    states, probs, experts = [x0.T], [mu], [x]
    late, x_start, P_start, mu_start = late_starts(start), x[0], P[0], mu[:, :1]
    for t in range(1, T):
        try:
            x, P, mu, xf = step(x, P, mu, zz[t], miss[t], *consts)
        except Exception as err:  # noqa: BLE001 - any compiler failure: fall back to eager, say why once
            if t > 1 or step is fused_step:
                raise
            _broken = True
            log.warning("torch.compile of the IMM step failed (%s: %s); using the eager path", type(err).__name__, err)
            return None
        if t <= late:  # tracks that start at t or later hold their start (runner.run's start); batch last
            h = t <= start
            x, P, mu = torch.where(h, x_start, x), torch.where(h, P_start, P), torch.where(h, mu_start, mu)
            xf = _dot(mu[:, None], x, -3)
        states.append(xf), probs.append(mu)
        if return_experts:
            experts.append(x)
    states = torch.stack(states).permute(2, 0, 1)  # [B, T, 9]
    probs = torch.stack(probs).permute(2, 0, 1)
    experts = torch.stack(experts).permute(3, 0, 1, 2) if return_experts else None  # [B, T, M, 9]
    return states, probs, experts
