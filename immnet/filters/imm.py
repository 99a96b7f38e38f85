"""The interacting multiple model filter (Blom & Bar-Shalom), batched, experts stacked on ``M``.

One step, in the order of FilterPy's ``IMMEstimator`` (``predict`` then ``update``), with mode
probabilities ``mu_{t-1}`` ``[B, M]`` and the Markov transition ``Pi[i, j] = P(j at t | i at t-1)``:

1. mixing: ``cbar_j = sum_i Pi_ij mu_i``, ``w_ij = Pi_ij mu_i / cbar_j``,
   ``x0_j = sum_i w_ij x_i``, ``P0_j = sum_i w_ij (P_i + (x_i - x0_j)(x_i - x0_j)^T)``;
2. mode-matched prediction: ``x_j = F_j x0_j``, ``P_j = F_j P0_j F_j^T + Q_j``;
3. mode-matched update with ``z_t`` (``immnet.imm.kalman.update``), log-likelihoods ``l_j``;
4. mode update in log space: ``log mu_j = log cbar_j + l_j - logsumexp_k(log cbar_k + l_k)``
   (a missed detection gives ``l_j = 0``, so ``mu = cbar``);
5. combination: ``x = sum_j mu_j x_j`` (and ``P = sum_j mu_j (P_j + (x_j - x)(x_j - x)^T)``).

Everything is one batched tensor expression per stage: no loop over tracks or experts. The stages are
``immnet.imm``'s, in ``immnet.imm.runner.run``'s loop; ``_imm_filter_lean`` and ``immnet.filters.imm_fused``
are the same equations rearranged for speed where every track shares ``F`` and ``Q`` (the tests hold them
to the core's loop and to FilterPy).
"""

from __future__ import annotations

import torch

from immnet.imm.kalman import _as_cov
from immnet.imm.runner import late_starts, linear_transition, run

VEL_STD = 300.0
"""Initial velocity standard deviation (m/s), every axis: covers the 340 m/s speed bound."""
ACC_STD = 10.0
"""Initial acceleration standard deviation (m/s^2), every axis."""


def first_detection(z: torch.Tensor) -> torch.Tensor:
    """The scan of each track's first detection ``[B]`` (long; 0 for a track with none) of ``z [B, T, 3]``."""
    finite = ~torch.isnan(z).any(-1)  # [B, T]
    return torch.where(finite.any(-1), finite.long().argmax(-1), torch.zeros_like(finite[:, 0], dtype=torch.long))


def initial_state(z: torch.Tensor, r, vel_std: float = VEL_STD, acc_std: float = ACC_STD, cov0=None):
    """``x0``, ``P0`` from the first measurement of each track (docs/spec.md section 3).

    ``z [B, T, 3]``; ``r`` the filter's assumed measurement standard deviation (scalar or ``[B]``).
    ``x0 = [z0x, 0, 0, z0y, 0, 0, z0z, 0, 0]`` and ``P0 = diag(r^2, vel_std^2, acc_std^2)`` per axis; ``cov0 [B, 3, 3]``
    (given, ``r`` unused): the first detection's own measurement covariance as ``P0``'s position block.
    A track whose first measurement is missing starts at its first detected position (zeros if it
    has none), at the scan of that detection (``first_detection``; give it to ``imm_filter``/``runner.run`` as
    ``start``, so that the filters hold this state until then and never filter that detection a second time); the
    methods output NaN until that detection (``immnet.filters.base.output``).
    """
    first = first_detection(z)
    z0 = z.gather(1, first[:, None, None].expand(-1, 1, 3))[:, 0]
    z0 = torch.nan_to_num(z0, nan=0.0)
    B = z.shape[0]
    x0 = z.new_zeros(B, 9)
    x0[:, 0::3] = z0
    r2 = None if cov0 is not None else torch.as_tensor(r, dtype=z.dtype, device=z.device) ** 2
    diag = z.new_zeros(B, 9)
    if cov0 is None:
        diag[:, 0::3] = r2.reshape(-1, 1) if r2.dim() else r2
    diag[:, 1::3] = vel_std**2
    diag[:, 2::3] = acc_std**2
    P0 = torch.diag_embed(diag)
    if cov0 is not None:
        P0[:, 0::3, 0::3] = cov0.to(P0)
    return x0, P0


def imm_filter(z, x0, P0, F, Q, R, Pi, mu0, return_experts: bool = False, compile: bool = False, general: bool = False,
               return_cov: bool = False, start: torch.Tensor | None = None, robust: float | None = None):
    """Run the IMM over ``z [B, T, 3]`` from ``x0 [B, 9]``, ``P0 [B, 9, 9]`` and ``mu0 [M]``.

    At ``t = 0`` the output is the initial state (every expert at ``x0, P0``); steps ``t >= 1``
    filter ``z_t``. Returns ``state [B, T, 9]``, ``probs [B, T, M]`` and, with ``return_experts``,
    the experts' posteriors ``[B, T, M, 9]`` (else None).

    ``F``, ``Q`` are ``[M, 9, 9]`` (every track's), ``[B, M, 9, 9]`` (one interval per track) or
    ``[B, T, M, 9, 9]`` (one per track and scan). The scan loop is ``immnet.imm.runner.run``; where every
    track shares ``F`` and ``Q`` the same equations run rearranged for speed (``_imm_filter_lean``;
    ``general=True`` runs the core's loop anyway). ``compile=True`` runs the step of
    ``immnet.filters.imm_fused`` through ``torch.compile`` there (the first call per dtype, device and model
    count compiles, seconds); if compiling fails it logs a warning and runs the eager path. ``return_cov`` runs the
    core's loop and returns a fourth output, the combined covariance ``[B, T, 9, 9]``. ``start [B]``: the scan at
    which each track starts from ``x0``, ``P0`` (``first_detection``; ``runner.run``'s), None: scan 0.
    ``R``: a variance (a number or ``[B]``), one covariance ``[3, 3]`` or one per track ``[B, 3, 3]``, or one per
    detection ``[B, T, 3, 3]`` (``immnet.imm.measurement.PerDetection``: finite where a scan is missed). ``robust``:
    Huber's ``k`` of the update (``immnet.imm.kalman``), None: the plain update (it runs the core's loop).
    """
    B, T, _ = z.shape
    M = Pi.shape[-1]
    R = torch.as_tensor(R, dtype=z.dtype, device=z.device)
    if not (general or return_cov or robust is not None) and _lean_ok(F, Q, R, M, x0.shape[-1]):
        if compile and R.dim() < 4:
            from immnet.filters.imm_fused import imm_filter_fused

            out = imm_filter_fused(z, x0, P0, F, Q, R, Pi, mu0, return_experts, start=start)
            if out is not None:
                return out
        return _imm_filter_lean(z, x0, P0, F, Q, R, Pi, mu0, return_experts, start)
    x = x0.unsqueeze(1).expand(B, M, 9).contiguous()
    P = P0.unsqueeze(1).expand(B, M, 9, 9).contiguous()
    mu = mu0.to(z).expand(B, M).contiguous()
    if R.dim() == 3:
        R = R[:, None]  # one covariance per track [B, 3, 3], for every filter
    if R.dim() == 4:
        per_detection = R
        R = lambda t: per_detection[:, t, None]  # noqa: E731 (each detection's [B, 1, 3, 3], for every filter)
    return run(z, x, P, mu, Pi, linear_transition(F, Q), R, return_experts=return_experts, return_cov=return_cov,
               start=start, robust=robust)


_SMALL = 1024


def _lean_ok(F, Q, R, M, n) -> bool:
    """Whether ``_imm_filter_lean`` applies: the same ``F``, ``Q`` for every track, a scalar or 3x3 ``R`` or one
    per detection ``[B, T, 3, 3]``."""
    R = torch.as_tensor(R)
    return (
        n == 9 and F.shape == (M, 9, 9) and Q.dim() <= 3 and Q.shape[-2:] == (9, 9) and Q.shape[0] in (1, M)
        and (R.numel() == 1 or R.shape == (3, 3) or R.dim() == 4)
    )


def _kron_t(F):
    """``(F (x) F)^T``, symmetrized, ``[M, n^2, n^2]``: ``vec(P) @ K`` is ``vec(F sym(P) F^T)``."""
    M, n, _ = F.shape
    K = torch.einsum("mli,mkj->mlkij", F, F).reshape(M, n * n, n * n)
    K = 0.5 * (K + K.reshape(M, n, n, n * n).transpose(1, 2).reshape(M, n * n, n * n))
    return K.transpose(1, 2).contiguous()


def _imm_filter_lean(z, x0, P0, F, Q, R, Pi, mu0, return_experts, start=None):
    """``imm_filter`` for shared ``F``, ``Q`` ``[M, 9, 9]``: the same steps, fewer and larger ops.

    Experts lie first (``x [M, B, 9]``, ``P [M, B, 81]``) so that the prediction of every track is one
    GEMM per model, ``vec(P) (F (x) F)^T + vec(Q)`` (symmetrizing ``P`` on the way, which replaces the
    update's symmetrization), and the update uses the position block of ``P`` directly (``H`` selects
    positions) with the adjugate inverse of ``S``. Missed detections zero the gain and the likelihood,
    which leaves the prior exactly; steps without one skip that work. The mode update drops the
    constant ``-3/2 log 2 pi``, which cancels in the normalization.
    """
    B, T, _ = z.shape
    M = Pi.shape[-1]
    KT = _kron_t(F)
    Qv = Q.expand(M, 9, 9).reshape(M, 1, 81)
    Rm = _as_cov(R, 3, z)
    per_detection = Rm.dim() == 4  # [B, T, 3, 3]
    FT = F.transpose(1, 2)
    PiT = Pi.T.contiguous()
    tiny = torch.finfo(z.dtype).tiny
    x = x0.unsqueeze(0).expand(M, B, 9).contiguous()
    P = P0.reshape(1, B, 81).expand(M, B, 81).contiguous()
    mu = mu0.to(z).expand(B, M).contiguous()
    missed = torch.isnan(z).any(-1)  # [B, T]
    miss_t = missed.any(0).tolist()
    states, probs, experts = [x0], [mu], [x.transpose(0, 1)]
    late, mu_start, P_start = late_starts(start), mu.clone(), P0.reshape(B, 81)
    rows = torch.tensor([1, 2, 0, 2, 0, 1], device=z.device)
    small = B * M * M <= _SMALL
    for t in range(1, T):
        # 1. mixing, w^T [j, i, B]
        cbar = mu @ Pi
        wT = (PiT * mu[:, None, :] / cbar.clamp_min(tiny)[:, :, None]).permute(1, 2, 0)
        wx = wT[..., None]
        xm = (wx * x).sum(1)  # [j, B, 9]
        d = x - xm[:, None]  # [j, i, B, 9]: x_i - x0_j
        if small:  # few ops: E_ji = P_i + d_ji d_ji^T [j, i, B, 81], then the weighted sum over i
            Pm = (wx * torch.addcmul(P.view(M, B, 9, 9), d[..., :, None], d[..., None, :]).view(M, M, B, 81)).sum(1)
        else:  # many tracks: accumulate w_ji P_i + (w_ji d_ji) d_ji^T in place (no batches of tiny matmuls)
            wd = wx * d
            Pm = (wx[:, 0] * P[0]).view(M, B, 9, 9).addcmul_(wd[:, 0, ..., :, None], d[:, 0, ..., None, :])
            for i in range(1, M):
                Pm.view(M, B, 81).addcmul_(wx[:, i], P[i])
                Pm.addcmul_(wd[:, i, ..., :, None], d[:, i, ..., None, :])
            Pm = Pm.view(M, B, 81)
        # 2. prediction
        xp = torch.bmm(xm, FT)
        Pp = torch.baddbmm(Qv, Pm, KT)
        # 3. update with the positions
        PHt = Pp.view(M, B, 9, 9)[..., 0::3]  # [M, B, 9, 3]
        S = PHt[..., 0::3, :] + (Rm[:, t] if per_detection else Rm)
        S2 = S.index_select(-2, rows).unflatten(-2, (2, 3))  # rows (1, 2, 0) and (2, 0, 1)
        C = torch.linalg.cross(S2[..., 0, :, :], S2[..., 1, :, :], dim=-1)  # rows: cofactors of S's rows
        det = (S[..., 0, :] * C[..., 0, :]).sum(-1)
        Si = C.mT / det[..., None, None]
        zt = z[:, t]
        if miss_t[t]:
            zt = zt.nan_to_num(0.0)
        y = zt - xp[..., 0::3]
        if miss_t[t]:
            y = y.masked_fill(missed[:, t, None], 0.0)
        if small:
            K = PHt @ Si
        else:  # contractions over 3 as broadcast multiply-adds
            K = (PHt[..., 0:1] * Si[..., 0:1, :]).addcmul_(PHt[..., 1:2], Si[..., 1:2, :])
            K = K.addcmul_(PHt[..., 2:3], Si[..., 2:3, :])
        if miss_t[t]:
            K = K.masked_fill(missed[:, t, None, None], 0.0)
        if small:
            Siy = Si @ y[..., None]
            x = torch.baddbmm(xp.view(M * B, 9, 1), PHt.reshape(M * B, 9, 3), Siy.view(M * B, 3, 1)).view(M, B, 9)
            P = torch.baddbmm(Pp.view(M * B, 9, 9), K.view(M * B, 9, 3), PHt.mT.reshape(M * B, 3, 9), alpha=-1)
            q = (y[..., None, :] @ Siy).view(M, B)
        else:
            Siy = (Si * y[..., None, :]).sum(-1)
            x = xp + (PHt * Siy[..., None, :]).sum(-1)
            P = torch.addcmul(Pp.view(M, B, 9, 9), K[..., :, 0, None], PHt[..., None, :, 0], value=-1)
            P = P.addcmul_(K[..., :, 1, None], PHt[..., None, :, 1], value=-1)
            P = P.addcmul_(K[..., :, 2, None], PHt[..., None, :, 2], value=-1)
            q = (y * Siy).sum(-1)
        P = P.view(M, B, 81)
        # 4. mode probabilities, 5. fused state
        ll = (q + det.log()) * -0.5
        if miss_t[t]:
            ll = ll.masked_fill(missed[:, t], 0.0)
        mu = torch.softmax(cbar.log() + ll.T, -1)
        if t <= late:  # tracks that start at t or later hold their start (runner.run's start)
            h = (t <= start)[:, None]
            x, P, mu = torch.where(h, x0, x), torch.where(h, P_start, P), torch.where(h, mu_start, mu)
        xs = x.transpose(0, 1)
        states.append((mu[:, None, :] @ xs).squeeze(1) if small else (mu.T[..., None] * x).sum(0))
        probs.append(mu)
        if return_experts:
            experts.append(xs)
    stack = lambda seq: torch.stack(seq, 1)  # noqa: E731
    return stack(states), stack(probs), stack(experts) if return_experts else None
