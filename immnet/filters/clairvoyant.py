"""The clairvoyant Kalman filter: the bound no causal tracker beats on average (SPEC.md section 3).

It knows each trajectory's true mode sequence ``mode[t]``, turn rates ``turn_rate[t]`` and
measurement noise ``r``, and runs one Kalman filter with the truth's time-varying transition:

* ``F_t = F_CV``, ``F_CA`` or ``F_CT(turn_rate[t])`` by ``mode[t]`` (the step ``t-1 -> t``);
* the truth's process noise ``Q = sigma_q^2 G G^T``, ``G`` per axis ``[dt^2/2, dt, 0]``,
  ``sigma_q = 0.2``;  ``R = r^2 I``.

At the first step of a CA segment (``mode[t] = CA != mode[t-1]``, ``t >= 1``) the generator writes a
newly drawn acceleration into the state before ``F_CA``. The bound knows a switch happened, not
the draw: before predicting it resets the acceleration mean to 0, removes its correlations, and
sets its variance to that of the draw: horizontal magnitude ``a ~ U[0.5, 3]`` m/s^2 at a uniform
direction gives ``E[a_x^2] = E[a^2] / 2 = (3^3 - 0.5^3) / (3 * 2.5) / 2 = 1.7917`` per horizontal
axis; vertical ``U[-0.3, 0.3]`` gives ``0.6^2 / 12 = 0.03``.

It starts like every other method: from the first measurement (``initial_state`` with the true r),
except that where the first segment is CA it gives the acceleration the draw's variance above; no
estimate (NaN) before a track's first detection.

``SwitchClairvoyantKF`` is told less: the true mode sequence (so when a switch happens) and r, not
the turn rates. It runs an extended Kalman filter of ``[x, w]``: at every turn onset, and wherever
the turn rate changes within a turn (a soft-bound turn), ``w`` restarts from the prior of a 3D-LAST
turn, ``|w| ~ U[1, 10]`` deg/s in the mode's sign (mean 5.5, standard deviation 2.6 deg/s), and is
estimated from the measurements. It is a tighter reference than the bound for what a tracker that
detected every switch at once could reach.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

from immnet import keys
from immnet.filters.base import Method, as_dtype, batch_dt, output
from immnet.filters.imm import initial_state
from immnet.filters.kalman import predict, update
from immnet.motion import DEG, ca_matrix, ct_matrix, ct_propagate, cv_matrix, process_noise

CA_ACC_VAR = ((3.0**3 - 0.5**3) / (3.0 * 2.5) / 2.0, (3.0**3 - 0.5**3) / (3.0 * 2.5) / 2.0, 0.6**2 / 12.0)
"""Variance of a newly drawn CA acceleration per axis (x, y, z), from SPEC.md section 2."""

CV, CA, CT_POS, CT_NEG = 0, 1, 2, 3


class ClairvoyantKF(Method):
    """Kalman filter with the true modes, turn rates and r of each trajectory; a bound, not a tracker."""

    needs = (keys.MODE, keys.TURN_RATE, keys.R)
    ground_truth = True

    def __init__(self, sigma_q: float = 0.2, acc_var=CA_ACC_VAR, dtype="float64", name: str = "clairvoyant"):
        if sigma_q < 0:
            raise ValueError(f"sigma_q must be >= 0, got {sigma_q}")
        self.sigma_q, self.acc_var = float(sigma_q), tuple(float(v) for v in acc_var)
        self.dtype, self.name = as_dtype(dtype), name

    def _inputs(self, batch: TensorDict):
        """``z [B, T, 3]``, ``mode [B, T]``, ``turn_rate [B, T]``, ``r [B]`` in this method's dtype, and ``dt``."""
        self.check(batch)
        z = batch[keys.MEASUREMENTS].to(self.dtype)
        dev = z.device
        r = torch.as_tensor(batch[keys.R], dtype=self.dtype, device=dev).reshape(z.shape[0])
        dt = batch_dt(batch, self.dtype, dev)
        if not torch.all(dt == dt[0]):
            raise ValueError(f"{self.name} needs one dt for the whole batch, got several")
        return z, batch[keys.MODE].to(dev), batch[keys.TURN_RATE].to(self.dtype), r, float(dt[0])

    def _acc_cov(self, like: torch.Tensor) -> torch.Tensor:
        return torch.diag(torch.tensor(self.acc_var, dtype=like.dtype, device=like.device))

    @staticmethod
    def _ca_onset(x, P, new_ca, acc_P):
        """A CA segment starts: acceleration mean 0, uncorrelated, with the draw's variance ``acc_P``
        (on the first 9 components: the acceleration slots ``2::3`` of the state's 9-D part)."""
        if not new_ca.any():
            return x, P
        x, P = x.clone(), P.clone()
        acc = torch.tensor([2, 5, 8], device=x.device)
        x[new_ca.nonzero()[:, 0][:, None], acc] = 0.0
        P[new_ca, :, 2:9:3] = 0.0
        P[new_ca, 2:9:3, :] = 0.0
        P[new_ca, 2:9:3, 2:9:3] = acc_P
        return x, P

    def track(self, batch: TensorDict) -> TensorDict:
        z, mode, w, r, d = self._inputs(batch)
        dtype, dev = z.dtype, z.device
        B, T, _ = z.shape
        Fcv, Fca = cv_matrix(d, dtype, dev), ca_matrix(d, dtype, dev)
        Q = process_noise(self.sigma_q, d, "white", dtype=dtype, device=dev)
        R = r**2
        acc_P = self._acc_cov(z)
        x, P = initial_state(z, r)
        first_ca = mode[:, 0] == CA  # the generator writes the first CA segment's draw into x_0
        P[first_ca, 2::3, 2::3] = acc_P
        states = z.new_empty(B, T, 9)
        states[:, 0] = x
        for t in range(1, T):
            m = mode[:, t]
            F = torch.where((m == CV)[:, None, None], Fcv, torch.where((m == CA)[:, None, None], Fca, ct_matrix(w[:, t], d, dtype, dev)))
            x, P = self._ca_onset(x, P, (m == CA) & (mode[:, t - 1] != CA), acc_P)
            x, P = predict(x, P, F, Q)
            x, P, _ = update(x, P, z[:, t], None, R)
            states[:, t] = x
        return output(states, measurements=z)


TURN_PRIOR_DEG = (5.5, 9.0 / 12.0**0.5)
"""Mean and standard deviation of a 3D-LAST turn rate's magnitude, ``U[1, 10]`` deg/s (SPEC.md section 2)."""


class SwitchClairvoyantKF(ClairvoyantKF):
    """Knows the true modes (the switches) and r, estimates each turn's rate: a tighter reference."""

    def __init__(self, sigma_q: float = 0.2, acc_var=CA_ACC_VAR, turn_prior_deg=TURN_PRIOR_DEG, dtype="float64",
                 name: str = "clairvoyant-switch"):
        super().__init__(sigma_q, acc_var, dtype, name)
        mean, std = (float(v) for v in turn_prior_deg)
        if not (mean > 0 and std >= 0):
            raise ValueError(f"turn_prior_deg needs a mean > 0 and a std >= 0, got {turn_prior_deg}")
        self.w_mean, self.w_var = mean * DEG, (std * DEG) ** 2

    def track(self, batch: TensorDict) -> TensorDict:
        from immnet.stages.filtering import ct_rate_derivative

        z, mode, rate, r, d = self._inputs(batch)
        dtype, dev = z.dtype, z.device
        B, T, _ = z.shape
        H = torch.eye(10, dtype=dtype, device=dev)[0:9:3]  # the positions of [x, w]
        Fcv, Fca = torch.zeros(10, 10, dtype=dtype, device=dev), torch.zeros(10, 10, dtype=dtype, device=dev)
        Fcv[:9, :9], Fca[:9, :9] = cv_matrix(d, dtype, dev), ca_matrix(d, dtype, dev)
        Q = torch.zeros(10, 10, dtype=dtype, device=dev)
        Q[:9, :9] = process_noise(self.sigma_q, d, "white", dtype=dtype, device=dev)
        acc_P = self._acc_cov(z)
        x9, P9 = initial_state(z, r)
        x = torch.cat([x9, torch.zeros(B, 1, dtype=dtype, device=dev)], -1)
        P = torch.zeros(B, 10, 10, dtype=dtype, device=dev)
        P[:, :9, :9] = P9
        P[mode[:, 0] == CA, 2::3, 2::3] = acc_P
        R = r**2
        states = z.new_empty(B, T, 9)
        states[:, 0] = x[:, :9]
        for t in range(T):
            m = mode[:, t]
            turn = m >= CT_POS
            onset = turn & ((m != mode[:, t - 1]) | (rate[:, t] != rate[:, t - 1])) if t else turn
            if onset.any():  # a turn starts (or changes rate): w from the prior, in the mode's sign
                x, P = x.clone(), P.clone()
                sign = torch.where(m[onset] == CT_POS, 1.0, -1.0).to(dtype)  # python floats in where: float32
                x[onset, 9] = sign * self.w_mean
                P[onset, 9, :] = 0.0
                P[onset, :, 9] = 0.0
                P[onset, 9, 9] = self.w_var
            if t == 0:
                continue
            x, P = self._ca_onset(x, P, (m == CA) & (mode[:, t - 1] != CA), acc_P)
            w = x[:, 9]
            J = torch.where((m == CV)[:, None, None], Fcv, Fca).expand(B, 10, 10).clone()
            J_turn = torch.zeros_like(J)
            J_turn[:, :9, :9] = ct_matrix(w, d, dtype, dev)
            J_turn[:, :9, 9] = ct_rate_derivative(x[:, :9], w, d)
            J_turn[:, 9, 9] = 1.0
            J = torch.where(turn[:, None, None], J_turn, J)
            prior = (J @ x.unsqueeze(-1)).squeeze(-1)
            x = torch.where(turn[:, None], torch.cat([ct_propagate(x[:, :9], w, d), w[:, None]], -1), prior)
            P = J @ P @ J.transpose(-1, -2) + Q
            x, P, _ = update(x, P, z[:, t], H, R)  # a missed detection: the prior stands
            states[:, t] = x[:, :9]
        return output(states, measurements=z)
