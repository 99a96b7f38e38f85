"""The model-based IMM's scan loop: ``immnet.imm``'s stages in order, over a whole sequence.

One scan, for every track at once (FilterPy's ``IMMEstimator`` order)::

    w = mixing_weights(mu, Pi)           x0, P0 = mix(w, x, P, onset)           # the interaction
    xp, Pp = transition(t, x0, P0)       # each filter's mode-matched prediction over t-1 -> t
    x, P, l = update(xp, Pp, z_t, R_t)   # the Kalman update; a NaN row is a missed detection (l = 0)
    mu = mode_update(log cbar, l)        x_t = combine(x, mu)

``transition(t, x0, P0)`` is the motion: a linear model set gives ``F x0`` and ``F P0 F^T + Q`` with ``F``,
``Q`` of the interval before scan ``t`` (``linear_transition``; one interval per track, ``dt [B, T]``),
the clairvoyant bound the truth's model of each track at ``t``. ``oracle [B, T]`` replaces the
Bayesian mode update by the truth's mode (a bound, not a tracker: the interaction then takes each
filter's prior from the true mode's filter, with the onset priors where the mode switched).

A Kalman filter is the case of one model; the paper's IMMs and IMM-Tuned the case of a linear model set
without onset priors. IMMNet's filter experts run the same stages inside ``immnet.stages`` (the
model-based IMM-EKF is one of its configurations).
"""

from __future__ import annotations

from typing import Callable

import torch

from immnet.imm.interaction import combine, enter, mix, mixing_weights, mode_update
from immnet.imm.kalman import predict, update


def linear_transition(F: torch.Tensor, Q: torch.Tensor) -> Callable:
    """``transition`` of a linear model set: ``F``, ``Q`` ``[M, n, n]`` (shared), ``[B, M, n, n]`` (one
    interval per track) or ``[B, T, M, n, n]`` (one per track and scan: the interval before scan ``t``)."""
    per_scan = F.dim() == 5

    def transition(t: int, x0: torch.Tensor, P0: torch.Tensor):
        Ft, Qt = (F[:, t], Q[:, t]) if per_scan else (F, Q)
        return predict(x0, P0, Ft, Qt)

    return transition


def late_starts(start: torch.Tensor | None) -> int:
    """The last scan at which a track starts (``start [B]``, one host read per sequence), 0 where none is given."""
    return 0 if start is None or start.numel() == 0 else int(start.max())


def run(
    z: torch.Tensor,
    x: torch.Tensor,
    P: torch.Tensor,
    mu: torch.Tensor,
    Pi: torch.Tensor,
    transition: Callable,
    R,
    onset: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
    oracle: torch.Tensor | None = None,
    return_experts: bool = False,
    H: torch.Tensor | None = None,
    return_cov: bool = False,
    start: torch.Tensor | None = None,
    restart: torch.Tensor | None = None,
    robust: float | None = None,
    measure: Callable | None = None,
    reacquire=None,
):
    """Filter ``z [B, T, m]`` from the filters' states at scan 0, ``x [B, M, n]``, ``P [B, M, n, n]``, and
    ``mu [B, M]``; ``Pi [M, M]``; ``R`` the measurement variance (a scalar, ``[B]``, or a covariance
    ``[B, 1, 3, 3]``) or a callable ``R(t)`` of the scan; ``onset`` ``onset_priors``' ``(keep, mean, cov)``;
    ``H [m, n]`` the measurement matrix (None: the positions of the 9-D state, ``m = 3``).

    Returns ``state [B, T, n]`` (at scan 0 the combination of the given states), ``probs [B, T, M]`` and,
    with ``return_experts``, the filters' posteriors ``[B, T, M, n]`` (else None); with ``return_cov`` a fourth,
    the combined covariance ``[B, T, n, n]`` (``combine``'s moment match).

    ``start [B]`` (long): the scan at which each track starts, where the given states are its estimate (the
    first detection's, ``immnet.filters.imm.first_detection``); until then the filters hold those states and
    ``mu`` (an oracle's modes stand), so that a track whose first scans are missed starts at its first detection
    and filters it once. None: every track starts at scan 0. ``restart [B, T]`` (bool, with ``onset``): where the
    truth draws anew what its mode draws without a mode switch (a turn's new rate within a turn), the filters enter
    from themselves with their onset priors too, after the mix. ``robust``: Huber's ``k`` of the update
    (``immnet.imm.kalman``'s module doc: an isolated far plot's, each track's ``spare`` carried from scan to scan), None:
    the plain update. ``measure(t, xp, Pp, spare) -> (x, P, l[, far])``: the update of scan ``t`` in place of the
    linear one (a nonlinear measurement model's, ``immnet.imm.measurement.Polar``; ``z``, ``H``, ``R`` and ``robust``
    are then its business, ``z`` only says which scans are detections). ``reacquire``: an
    ``immnet.imm.reacquire.Restarts`` (the positions' ``H``, the linear update): a track whose run of far detections
    agrees restarts at the last of them (that module's doc); None: none.
    """
    B, T, _ = z.shape
    M = x.shape[1]
    if reacquire is not None and (measure is not None or H is not None):
        raise ValueError("re-acquisition takes the linear update of the positions (H None, no measure)")
    onehot = None if oracle is None else torch.nn.functional.one_hot(oracle.long(), M).to(z.dtype)  # [B, T, M]
    if onehot is not None:
        mu = onehot[:, 0]
    states, probs = z.new_empty(B, T, x.shape[-1]), z.new_empty(B, T, M)
    experts = z.new_empty(B, T, M, x.shape[-1]) if return_experts else None
    covs = z.new_empty(B, T, x.shape[-1], x.shape[-1]) if return_cov else None

    def record(t: int, x, P, mu):
        """Scan ``t``'s outputs: the combined state (and covariance), the mode probabilities and the filters'."""
        states[:, t], cov = combine(x, P if return_cov else None, mu)
        probs[:, t] = mu
        if return_cov:
            covs[:, t] = cov
        if return_experts:
            experts[:, t] = x

    record(0, x, P, mu)
    last, initial = late_starts(start), (x, P, mu)  # the last scan a track is held at, and what it holds
    spare = None if robust is None else torch.zeros(B, 1, dtype=torch.bool, device=z.device)  # kalman's module doc
    watching = None if reacquire is None else reacquire.begin(x, P)
    restarts = None if restart is None else restart.any(0).tolist()  # one host read per sequence
    for t in range(1, T):
        w = mixing_weights(mu, Pi)
        x0, P0 = mix(w, x, P, onset)
        if restarts is not None and restarts[t]:
            again = restart[:, t, None, None]
            xe, Pe = enter(x0, P0, *onset)  # idempotent for what entered from another filter
            x0, P0 = torch.where(again, xe, x0), torch.where(again[..., None], Pe, P0)
        xp, Pp = transition(t, x0, P0)
        if measure is not None:
            x, P, ll, *after = measure(t, xp, Pp, spare)
        else:
            Rt = torch.as_tensor(R(t) if callable(R) else R, dtype=z.dtype, device=z.device)
            Rt = Rt[:, None] if Rt.dim() == 1 else Rt  # a variance per track [B], for every filter
            zt = z[:, t]
            if watching is not None:  # re-acquisition: a far detection may be gated out, a track restarted
                watching, zt, restarting = reacquire.observe(watching, t, zt, Rt, xp, Pp, start)
            x, P, ll, *after = update(xp, Pp, zt[:, None], H, Rt, robust=robust, spare=spare)
        if after:
            spare = after[0]
        if onehot is not None:
            mu = onehot[:, t]
        else:
            mu = mode_update(torch.log(mu @ Pi), ll)
        if t <= last:  # the tracks that start at scan t or later back at their starting values
            h = t <= start.to(x.device)
            x, P, held_mu = (torch.where(h.view(-1, *[1] * (v.dim() - 1)), v0, v) for v, v0 in zip((x, P, mu), initial))
            mu = held_mu if onehot is None else mu  # an oracle's modes stand
            if spare is not None:  # a track starts at its first detection with no far plot before it
                spare = spare & ~h[:, None]
        if watching is not None:
            x, P, mu = reacquire.restart(restarting, z[:, t], Rt, x, P, mu)
            if spare is not None:
                spare = spare & ~restarting[:, None]
        record(t, x, P, mu)
    return (states, probs, experts, covs) if return_cov else (states, probs, experts)
