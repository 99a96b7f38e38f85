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
``immnet.imm``'s, in ``immnet.imm.runner.run``'s loop, the one eager scan loop of every model-based IMM;
``imm_filter(compile=True)`` runs ``immnet.filters.imm_fused``, the same equations written for ``torch.compile``
where every track shares ``F`` and ``Q`` (the tests hold it to the core's loop and to FilterPy).
"""

from __future__ import annotations

import torch

from immnet.imm.kalman import _as_cov, start_state
from immnet.imm.runner import linear_transition, run

VEL_STD = 300.0
"""Initial velocity standard deviation (m/s), every axis: covers the 340 m/s speed bound."""
ACC_STD = 10.0
"""Initial acceleration standard deviation (m/s^2), every axis."""


def first_detection(z: torch.Tensor) -> torch.Tensor:
    """The scan of each track's first detection ``[B]`` (long; 0 for a track with none) of ``z [B, T, 3]``."""
    return (~torch.isnan(z).any(-1)).long().argmax(-1)  # argmax: the first detected scan, 0 where none is


def initial_state(z: torch.Tensor, r, vel_std: float = VEL_STD, acc_std: float = ACC_STD, cov0=None,
                  vz_std: float | None = None):
    """``x0``, ``P0`` from the first measurement of each track (docs/spec.md section 3).

    ``z [B, T, 3]``; ``r`` the filter's assumed measurement standard deviation (scalar or ``[B]``).
    ``x0 = [z0x, 0, 0, z0y, 0, 0, z0z, 0, 0]`` and ``P0 = diag(r^2, vel_std^2, acc_std^2)`` per axis; ``cov0 [B, 3, 3]``
    (given, ``r`` unused): the first detection's own measurement covariance as ``P0``'s position block; ``vz_std``: a
    prior on the vertical speed (``start_state``).
    A track whose first measurement is missing starts at its first detected position (zeros if it
    has none), at the scan of that detection (``first_detection``; give it to ``imm_filter``/``runner.run`` as
    ``start``, so that the filters hold this state until then and never filter that detection a second time); the
    methods output NaN until that detection (``immnet.filters.base.output``).
    """
    first = first_detection(z)
    z0 = z.gather(1, first[:, None, None].expand(-1, 1, 3))[:, 0]
    z0 = torch.nan_to_num(z0, nan=0.0)
    if cov0 is None:
        r2 = torch.as_tensor(r, dtype=z.dtype, device=z.device) ** 2
        cov0 = _as_cov(r2.expand(z.shape[0]), 3, z)
    return start_state(z0, cov0, vel_std, acc_std, vz_std)


def imm_filter(z, x0, P0, F, Q, R, Pi, mu0, return_experts: bool = False, compile: bool = False,
               return_cov: bool = False, start: torch.Tensor | None = None, robust: float | None = None, reacquire=None,
               measure=None):
    """Run the IMM over ``z [B, T, 3]`` from ``x0 [B, 9]``, ``P0 [B, 9, 9]`` and ``mu0 [M]``.

    At ``t = 0`` the output is the initial state (every expert at ``x0, P0``); steps ``t >= 1``
    filter ``z_t``. Returns ``state [B, T, 9]``, ``probs [B, T, M]`` and, with ``return_experts``,
    the experts' posteriors ``[B, T, M, 9]`` (else None).

    ``F``, ``Q`` are ``[M, 9, 9]`` (every track's), ``[B, M, 9, 9]`` (one interval per track) or
    ``[B, T, M, 9, 9]`` (one per track and scan). The scan loop is ``immnet.imm.runner.run``. ``compile=True``
    runs the step of ``immnet.filters.imm_fused`` through ``torch.compile`` where every track shares ``F``, ``Q`` and
    ``R`` (the first call per dtype, device and model count compiles, seconds); if compiling fails it logs a warning
    and runs the core's loop. ``return_cov``: a fourth output, the combined covariance ``[B, T, 9, 9]``. ``start [B]``: the scan at
    which each track starts from ``x0``, ``P0`` (``first_detection``; ``runner.run``'s), None: scan 0.
    ``R``: a variance (a number or ``[B]``), one covariance ``[3, 3]`` or one per track ``[B, 3, 3]``, or one per
    detection ``[B, T, 3, 3]`` (``immnet.imm.measurement.PerDetection``: finite where a scan is missed). ``robust``:
    Huber's ``k`` of the update (``immnet.imm.kalman``), None: the plain update. ``reacquire``: ``runner.run``'s
    re-acquisition (``immnet.imm.reacquire.Restarts``), None: none. ``measure``: ``runner.run``'s update in place of
    the linear one (``immnet.imm.measurement.Polar.measure``; ``R`` is then unused, and ``robust`` is the update's).
    """
    B, T, _ = z.shape
    M = Pi.shape[-1]
    R = torch.as_tensor(0.0 if measure is not None else R, dtype=z.dtype, device=z.device)  # R unused with measure
    eager = return_cov or robust is not None or reacquire is not None or measure is not None
    if compile and not eager and _fused_ok(F, Q, R, M, x0.shape[-1]):
        from immnet.filters.imm_fused import imm_filter_fused

        out = imm_filter_fused(z, x0, P0, F, Q, R, Pi, mu0, return_experts, start=start)
        if out is not None:
            return out
    x = x0.unsqueeze(1).expand(B, M, 9).contiguous()
    P = P0.unsqueeze(1).expand(B, M, 9, 9).contiguous()
    mu = mu0.to(z).expand(B, M).contiguous()
    if R.dim() == 3:
        R = R[:, None]  # one covariance per track [B, 3, 3], for every filter
    if R.dim() == 4:
        per_detection = R
        R = lambda t: per_detection[:, t, None]  # noqa: E731 (each detection's [B, 1, 3, 3], for every filter)
    return run(z, x, P, mu, Pi, linear_transition(F, Q), R, return_experts=return_experts, return_cov=return_cov,
               start=start, robust=robust, reacquire=reacquire, measure=measure)


def _fused_ok(F, Q, R, M, n) -> bool:
    """Whether ``immnet.filters.imm_fused`` applies: the same ``F``, ``Q`` for every track, a scalar or one 3x3 ``R``."""
    return (
        n == 9 and F.shape == (M, 9, 9) and Q.dim() <= 3 and Q.shape[-2:] == (9, 9) and Q.shape[0] in (1, M)
        and (R.numel() == 1 or R.shape == (3, 3))
    )
