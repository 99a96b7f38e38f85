"""IMM-EKF: the IMM a tracking engineer would build from the 3D-LAST generator's statistics.

The paper's IMM variants (``IMMTracker``) are linear: CT at a fixed turn rate, a CA model that must
find each new acceleration through its process noise, and one ``r`` for every track. This method
is the model-based counterpart of IMMNet's filter experts, told what the data's *statistics* are
(docs/spec.md section 2), never a trajectory's truth:

* four mode-matched filters, CV, CA, CT+ and CT-, all over the augmented state ``[x (9), w]``; the
  turn filters are extended Kalman filters that estimate their turn rate ``w`` (its Jacobian
  ``immnet.stages.filtering.ct_rate_derivative``), bounded to ``1 <= |w| <= 30`` deg/s in their sign
  (``TURN_RATE_LIMIT_DEG``, what an aircraft can fly: the prior's 10 deg/s as a bound would hold a
  faster turn's rate below the truth, and the track would fall behind it; docs/robustness.md);
* the truth's process noise (white acceleration, ``sigma_q`` 0.2 m/s^2 on position and velocity);
  a CA segment's acceleration is constant, a turn's rate too (``rate_noise_deg`` per scan, 0);
* the IMM interaction (Blom & Bar-Shalom) with the generator's **onset priors**: where the mixed
  estimate of filter ``j`` takes filter ``i != j``'s posterior, i.e. where a switch into ``j`` is
  hypothesized, the quantity the generator draws anew at that switch is replaced by its prior: into
  CA, the acceleration (mean 0, the draw's variance ``CA_ACC_VAR``, uncorrelated); into a turn, the
  turn rate (``+/- 5.5`` deg/s, standard deviation 2.6 deg/s: ``|w| ~ U[1, 10]``);
* a Markov chain with ``p_stay`` per scan (the rest shared evenly), mu0 uniform;
* the measurement noise ``r`` estimated per track from the third differences of the altitude
  measurements (``E[(d^3 z)^2] = 20 r^2``), a running mean from a prior ``r0`` worth ``k0``
  samples, as IMMNet's filter experts do (``r`` fixed instead if given).

With ``guard`` (``immnet.filters.guard.RangeGuard``: ``True`` for the generator's soft range and speed
bounds, or its fields as a dict) the Markov matrix becomes state-dependent per track and source filter,
and a turn entered at a bound starts at the bound's rate (``configs/methods/imm-ekf-guard.yaml``).

With ``adapt`` (``immnet.filters.adaptive.AdaptiveNoise``: ``True`` for its defaults, or its fields as a dict)
each track's white-acceleration noise is scaled by ``lambda`` in [1, 100], grown by covariance matching when
the smallest NIS of the four filters shows every one too confident: data with more
process noise than ``sigma_q`` (``configs/methods/imm-ekf-adaptive.yaml``; docs/baselines.md).

It starts like the other IMMs: from the first measurement (``initial_state``, with ``r0``), the CA
filter's acceleration at the draw's variance and the turn filters' rates at their prior; no
estimate (NaN) before a track's first detection.
``p_stay`` 0.995 was chosen on the dev set (seed 21), among 0.98, 0.99, 0.995, 0.998 and 0.999.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

from immnet import keys
from immnet.filters.adaptive import AdaptiveNoise
from immnet.filters.base import Method, as_dtype, batch_dt, output
from immnet.filters.clairvoyant import CA_ACC_VAR, TURN_PRIOR_DEG
from immnet.filters.guard import RangeGuard, blend_rate, fresh_share, guarded_transition
from immnet.filters.imm import initial_state
from immnet.filters.kalman import inv3, update
from immnet.filters.trackers import _positive, transition_matrix
from immnet.motion import DEG, TURN_RATE_LIMIT_DEG, ca_matrix, ct_matrix, ct_propagate, cv_matrix, process_noise

CV, CA, CT_POS, CT_NEG = 0, 1, 2, 3
RATE = 9  # the turn rate's slot in the augmented state
ACC = (2, 5, 8)


def altitude_noise_var(z: torch.Tensor, r0: float = 4.0, k0: float = 3.0) -> torch.Tensor:
    """Causal running estimate of ``r^2`` per scan ``[B, T]`` from ``z [B, T, 3]``.

    Each scan whose altitude and the three before it are detected adds ``(d^3 z)^2 / 20``
    (``d^3 z_t = z_t - 3 z_{t-1} + 3 z_{t-2} - z_{t-3}``, which cancels CV and CA motion); the
    estimate at scan ``t`` is ``(k0 r0^2 + sum) / (k0 + count)`` over scans up to and including ``t``.
    """
    alt = z[..., 2]
    d3 = torch.full_like(alt, float("nan"))
    d3[:, 3:] = alt[:, 3:] - 3.0 * alt[:, 2:-1] + 3.0 * alt[:, 1:-2] - alt[:, :-3]
    ok = torch.isfinite(d3)
    total = torch.cumsum(torch.where(ok, d3 * d3 / 20.0, 0.0), 1)
    count = torch.cumsum(ok.to(alt.dtype), 1)
    return (k0 * r0**2 + total) / (k0 + count)


class IMMEKF(Method):
    """IMM of CV, CA and two turn-rate-estimating EKFs, with the generator's onset priors (module doc)."""

    def __init__(
        self,
        p_stay: float = 0.995,
        sigma_q: float = 0.2,
        r: float | None = None,
        r0: float = 4.0,
        k0: float = 3.0,
        rate_bounds_deg: tuple[float, float] = (1.0, TURN_RATE_LIMIT_DEG),
        rate_noise_deg: float = 0.0,
        guard=None,
        adapt=None,
        dtype="float64",
        name: str = "imm-ekf",
    ):
        _positive("sigma_q", sigma_q)
        _positive("rate_noise_deg", rate_noise_deg)
        _positive("r0", r0, allow_zero=False)
        _positive("k0", k0, allow_zero=False)
        if r is not None:
            _positive("r", r, allow_zero=False)
        lo, hi = (float(v) for v in rate_bounds_deg)
        if not 0.0 < lo <= TURN_PRIOR_DEG[0] <= hi:
            raise ValueError(f"rate_bounds_deg must satisfy 0 < low <= {TURN_PRIOR_DEG[0]} <= high, got {rate_bounds_deg}")
        self.Pi = transition_matrix(p_stay, 4)
        self.sigma_q, self.r, self.r0, self.k0 = float(sigma_q), None if r is None else float(r), float(r0), float(k0)
        self.rate_lo, self.rate_hi, self.rate_noise = lo * DEG, hi * DEG, float(rate_noise_deg) * DEG
        self.guard = RangeGuard.from_config(guard)
        self.adapt = AdaptiveNoise.from_config(adapt)
        self.dtype, self.name = as_dtype(dtype), name

    def onset_priors(self, dtype=torch.float64, device=None):
        """What the interaction does to filter ``i``'s posterior entering filter ``j``'s mixed estimate:
        ``keep [M, M, 10]`` (1 where a component is kept, 0 where it is replaced), the prior's mean
        ``mean [M, M, 10]`` and covariance ``cov [M, M, 10, 10]`` on the replaced components."""
        M, n = 4, 10
        keep = torch.ones(M, M, n, dtype=dtype, device=device)
        mean = torch.zeros(M, M, n, dtype=dtype, device=device)
        cov = torch.zeros(M, M, n, n, dtype=dtype, device=device)
        w_mean, w_std = TURN_PRIOR_DEG[0] * DEG, TURN_PRIOR_DEG[1] * DEG
        for i in range(M):
            for j in range(M):
                if i == j:
                    continue
                if j == CA:
                    keep[i, j, list(ACC)] = 0.0
                    for a, v in zip(ACC, CA_ACC_VAR):
                        cov[i, j, a, a] = v
                elif j in (CT_POS, CT_NEG):
                    keep[i, j, RATE] = 0.0
                    mean[i, j, RATE] = w_mean if j == CT_POS else -w_mean
                    cov[i, j, RATE, RATE] = w_std**2
        return keep, mean, cov

    def track(self, batch: TensorDict) -> TensorDict:
        self.check(batch)
        z = batch[keys.MEASUREMENTS].to(self.dtype)
        dtype, dev = z.dtype, z.device
        dts = batch_dt(batch, dtype, dev)
        if not torch.all(dts == dts[0]):
            raise ValueError(f"{self.name} needs one dt for the whole batch, got several")
        d = float(dts[0])
        B, T, _ = z.shape
        M, n = 4, 10
        r2 = altitude_noise_var(z, self.r0, self.k0) if self.r is None else torch.full((B, T), self.r**2, dtype=dtype, device=dev)

        F = torch.zeros(2, n, n, dtype=dtype, device=dev)  # CV, CA; the rate slot carried unchanged
        F[0, :9, :9], F[1, :9, :9] = cv_matrix(d, dtype, dev), ca_matrix(d, dtype, dev)
        F[:, RATE, RATE] = 1.0
        Q = torch.zeros(M, n, n, dtype=dtype, device=dev)  # white acceleration (scaled by the adaptation)
        Q[:, :9, :9] = process_noise(self.sigma_q, d, "white", dtype=dtype, device=dev)
        Q_rate = torch.zeros(M, n, n, dtype=dtype, device=dev)
        Q_rate[2:, RATE, RATE] = self.rate_noise**2
        log_scale = torch.zeros(B, dtype=dtype, device=dev)  # AdaptiveNoise's log lambda per track
        H = torch.eye(n, dtype=dtype, device=dev)[0:9:3]
        keep, prior_mean, prior_cov = self.onset_priors(dtype, dev)
        keep2 = keep[..., :, None] * keep[..., None, :]
        Pi = self.Pi.to(dtype=dtype, device=dev)
        modes = torch.arange(M, device=dev)  # CV, CA, CT+, CT-
        if self.guard is not None:
            bound_rate = torch.tensor([0.0, 0.0, 1.0, -1.0], dtype=dtype, device=dev) * self.guard.rate_deg * DEG

        x9, P9 = initial_state(z, self.r if self.r is not None else self.r0)
        x = torch.zeros(B, M, n, dtype=dtype, device=dev)
        P = torch.zeros(B, M, n, n, dtype=dtype, device=dev)
        x[..., :9], P[..., :9, :9] = x9[:, None], P9[:, None]
        start = keep[CV]  # as if entering each filter from CV: CA's acceleration and the turns' rates at their prior
        x = x * start + prior_mean[CV]
        P = P * (start[..., :, None] * start[..., None, :]) + prior_cov[CV]
        mu = torch.full((B, M), 1.0 / M, dtype=dtype, device=dev)
        fresh = torch.zeros(B, M, dtype=dtype, device=dev)  # prior share entered at a speed bound (guard)

        states = z.new_empty(B, T, 9)
        probs = z.new_empty(B, T, M)
        states[:, 0], probs[:, 0] = x9, mu
        for t in range(1, T):
            # interaction: x0_j = sum_i mu_{i|j} x_{i->j}, with the onset priors where i != j
            Pi_t = Pi
            if self.guard is not None:  # state-dependent transitions (immnet.filters.guard)
                Pi_t, share, speed_share = guarded_transition(
                    Pi, self.guard.events(x[..., :9], x[..., RATE], d), modes, fresh)
            cbar = (mu[:, :, None] * Pi_t).sum(1)  # [B, j]
            w = mu[:, :, None] * Pi_t / cbar[:, None, :]  # mu_{i|j} [B, i, j]
            if self.guard is not None:
                fresh = fresh_share(w, speed_share)
            xc = x[:, :, None] * keep + prior_mean  # [B, i, j, n]
            Pc = P[:, :, None] * keep2 + prior_cov
            if self.guard is not None:  # a turn entered (or re-entered) at a range bound has the bound's rate
                xc, Pc = blend_rate(xc, Pc, share, bound_rate, (self.guard.rate_std_deg * DEG) ** 2, RATE)
            x0 = (w[..., None] * xc).sum(1)  # [B, j, n]
            dx = xc - x0[:, None]
            P0 = (w[..., None, None] * (Pc + dx[..., :, None] * dx[..., None, :])).sum(1)
            # mode-matched prediction: CV and CA linear, the turns by their EKF at their own rate
            rate = x0[:, 2:, RATE]
            J = torch.zeros(B, M, n, n, dtype=dtype, device=dev)
            J[:, :2] = F
            J[:, 2:, :9, :9] = ct_matrix(rate, d, dtype, dev)
            J[:, 2:, :9, RATE] = _rate_jacobian(x0[:, 2:, :9], rate, d)
            J[:, 2:, RATE, RATE] = 1.0
            xp = torch.cat(
                [(F @ x0[:, :2, :, None])[..., 0], torch.cat([ct_propagate(x0[:, 2:, :9], rate, d), rate[..., None]], -1)], 1
            )
            lam = AdaptiveNoise.scale(log_scale)[:, None, None, None]
            Pp = J @ P0 @ J.transpose(-1, -2) + lam * Q + Q_rate
            if self.adapt is not None:  # the smallest NIS of the mode-matched filters
                nu = z[:, t, None] - xp[..., 0:9:3]
                S = Pp[..., 0:9:3, :][..., 0:9:3] + r2[:, t, None, None, None] * torch.eye(3, dtype=dtype, device=dev)
                S_inv, _ = inv3(S)
                nis = (nu.unsqueeze(-2) @ S_inv @ nu.unsqueeze(-1))[..., 0, 0].min(-1).values
                log_scale = self.adapt.update(log_scale, nis, torch.isfinite(z[:, t]).all(-1))
            x, P, loglik = update(xp, Pp, z[:, t, None].expand(B, M, 3), H, r2[:, t, None].expand(B, M))
            x = x.clone()
            x[:, CT_POS, RATE] = x[:, CT_POS, RATE].clamp(self.rate_lo, self.rate_hi)
            x[:, CT_NEG, RATE] = x[:, CT_NEG, RATE].clamp(-self.rate_hi, -self.rate_lo)
            mu = torch.softmax(torch.log(cbar.clamp_min(1e-300)) + loglik, -1)
            states[:, t] = (mu[..., None] * x[..., :9]).sum(1)
            probs[:, t] = mu
        return output(states, {keys.MODE_PROBS: probs}, measurements=z)


def _rate_jacobian(x, w, dt):
    from immnet.stages.filtering import ct_rate_derivative  # the stages import the filters: import late

    return ct_rate_derivative(x, w, dt)
