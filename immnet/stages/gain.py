"""Stage 2, gain: one Kalman gain ``K^(i)`` (9 x 3) per expert.

``KalmanNetGain`` is KalmanNet's "architecture 2" (Revach et al. 2022): three GRUs tracking the
process-noise covariance Q, the state covariance Sigma and the innovation covariance S, with fully
connected layers FC1..FC7, for every expert at once (weights stacked on the expert dimension).
Causal features, each normalized by ``slog`` (``immnet.stages.features``):

* F1 ``z_t - z_{t-1}``, F2 ``z_t - H x_{t|t-1}^(i)``,
* F3 ``x_{t-1|t-1} - x_{t-2|t-2}``, F4 ``x_{t-1|t-1} - x_{t-1|t-2}^(i)``.

F1 and F3 are differences over an interval: where the step carries its interval (``("interval")``),
they are scaled to the nominal ``dt`` (``F dt / interval``, F3 by the previous scan's interval, carried),
so a network sees rates, not spans; at the nominal interval they are as above. With ``interval_input``
GRU_S also reads ``log(interval / dt)`` (a network trained over a range of intervals).

The network learns a bounded correction around its expert's steady-state Kalman gain:
``K = K_ss + K_scale * tanh(FC2(...))`` with FC2's last layer started small, so an untrained
expert is a steady-state Kalman filter and no finite input can produce an unbounded gain.

``AnalyticGain`` is the ablation: the textbook Kalman gain from each expert's covariance
``P^(i)_{t|t-1} = F^(i) P_{t-1|t-1} F^(i)T + Q^(i)``, ``K = P H^T (H P H^T + R)^-1``.
"""

from __future__ import annotations

import torch
from torch import nn

from immnet import keys
from immnet.imm.kalman import inv3, joseph
from immnet.imm.option import flag
from immnet.motion import POS, ModelSet
from immnet.stages.base import Stage, measured, per_expert
from immnet.stages.features import F1_SCALE, F2_SCALE, F3_SCALE, F4_SCALE, slog, state_scale
from immnet.stages.layers import StackedGRUCell, StackedLinear
from immnet.stages.predict import Predict
from immnet.stages.update import Update, innovation

_P = list(POS)


def steady_state(model_set: ModelSet, sigma_q: float, r: float, dt: float = 1.0, iters: int = 2000):
    """Steady-state prior covariance, gain and innovation covariance of each expert's KF (float64).

    Iterates the Riccati recursion ``P <- F (I - K H) P F^T + Q`` to convergence; returns
    ``(P [M, 9, 9], K [M, 9, 3], S [M, 3, 3])``.
    """
    F = model_set.F(dt)
    Q = model_set.Q(sigma_q, dt)
    R = r * r * torch.eye(3, dtype=torch.float64)
    P = Q + torch.eye(9, dtype=torch.float64) * 1e2
    for _ in range(iters):
        S = P[:, _P][:, :, _P] + R
        K = (inv3(S)[0] @ P[:, _P, :]).transpose(-1, -2)
        IKH = torch.eye(9, dtype=torch.float64).expand_as(P).clone()
        IKH[:, :, _P] -= K
        post = IKH @ P @ IKH.transpose(-1, -2) + K @ R @ K.transpose(-1, -2)
        P = F @ post @ F.transpose(-1, -2) + Q
    S = P[:, _P][:, :, _P] + R
    K = (inv3(S)[0] @ P[:, _P, :]).transpose(-1, -2)
    return P, K, S


class Gain(Stage):
    """The gain's role: each expert's Kalman gain (``("expert", "gain")`` ``[B, M, 9, 3]``), between the step's
    predict and update. A gain brings the stages around it (``stages``): these gains the shared ``Predict`` and
    ``Update`` and no interaction; filter experts (``immnet.stages.filtering``), which keep their own covariances and
    mode parameters and mix as an IMM, their own interaction, predict and update."""

    knock_out_correction = None
    """A gain with a learned state correction: the method that sets it alone to zero (``IMMNet.knock_out``)."""
    reacquire = None
    """A gain whose filter experts restart a track themselves: its rule (``immnet.imm.reacquire.Reacquire``;
    ``FilterGain``'s option), None for one without."""
    start_vz_std = None
    """A gain whose filter experts start a track with a prior on its vertical speed: that prior's std (m/s;
    ``FilterGain``'s option), None for one without."""

    def stages(self, model_set: ModelSet, dt: float) -> tuple[Stage | None, Stage, Stage]:
        """``(interaction or None, predict, update)`` of a step with this gain."""
        return None, Predict(model_set, dt), Update(model_set)


class KalmanNetGain(Gain):
    """KalmanNet architecture 2 per expert, stacked. ``in_mult`` and ``out_mult`` as in KalmanNet."""

    in_keys = [
        keys.MEASUREMENT, keys.PREV_MEASUREMENT, keys.FUSED, keys.PREV_FUSED,
        keys.EXPERT_PRIOR, keys.PREV_EXPERT_PRIOR, keys.EXPERT_HIDDEN, keys.PREV_INTERVAL,
    ]
    out_keys = [keys.EXPERT_GAIN, keys.EXPERT_HIDDEN, keys.PREV_INTERVAL]

    def __init__(
        self,
        model_set: ModelSet,
        dt: float = 1.0,
        in_mult: int = 5,
        out_mult: int = 4,
        init_sigma_q: float = 1.0,
        init_r: float = 4.0,
        gain_scale: tuple[float, float, float] = (1.0, 1.0, 0.5),
        init_out_scale: float = 0.01,
        interval_input: bool = False,
    ):
        super().__init__(model_set)
        self.dt, self.interval_input = dt, flag(interval_input, "interval_input")
        M, m, n = self.n_experts, 9, 3
        self.d_q, self.d_sigma, self.d_s = m * m, m * m, n * n
        self.fc5 = StackedLinear(M, m, m * in_mult)  # F4 -> GRU_Q
        self.gru_q = StackedGRUCell(M, m * in_mult, self.d_q)
        self.fc6 = StackedLinear(M, m, m * in_mult)  # F3 -> GRU_Sigma
        self.gru_sigma = StackedGRUCell(M, self.d_q + m * in_mult, self.d_sigma)
        self.fc1 = StackedLinear(M, self.d_sigma, n * n)
        self.fc7 = StackedLinear(M, 2 * n + int(self.interval_input), 2 * n * in_mult)  # F1, F2 -> GRU_S
        self.gru_s = StackedGRUCell(M, n * n + 2 * n * in_mult, self.d_s)
        d2 = self.d_s + self.d_sigma
        self.fc2a = StackedLinear(M, d2, d2 * out_mult)
        self.fc2b = StackedLinear(M, d2 * out_mult, m * n)
        self.fc3 = StackedLinear(M, self.d_s + m * n, m * m)
        self.fc4 = StackedLinear(M, self.d_sigma + m * m, self.d_sigma)
        with torch.no_grad():
            self.fc2b.weight.mul_(init_out_scale)
            self.fc2b.bias.zero_()
        self.h0_q = nn.Parameter(torch.zeros(M, self.d_q))
        self.h0_sigma = nn.Parameter(torch.zeros(M, self.d_sigma))
        self.h0_s = nn.Parameter(torch.zeros(M, self.d_s))
        self.base_gain(model_set, init_sigma_q, init_r, dt)
        row = state_scale(*gain_scale)
        self.register_buffer("K_scale", row[:, None].expand(9, 3).clone())
        self.register_buffer("f3_scale", state_scale(*F3_SCALE))
        self.register_buffer("f4_scale", state_scale(*F4_SCALE))

    def base_gain(self, model_set: ModelSet, sigma_q: float, r: float, dt: float) -> None:
        """The gain the learned correction is added to: the steady-state Kalman gain ``K_ss`` (a buffer)."""
        _, K_ss, _ = steady_state(model_set, sigma_q, r, dt)
        self.register_buffer("K_ss", K_ss.float())

    def knock_out(self) -> None:
        """Set FC2's last layer to zero: no learned correction, each expert its model-based base (here the
        steady-state Kalman gain; filter experts: the filter at its base process noise with its own Kalman gain,
        ``FilterGain``). For measuring what the learned part of a trained network is worth
        (docs/notebook/real-flights.md, "What each learned part is worth")."""
        with torch.no_grad():
            self.fc2b.weight.zero_()
            self.fc2b.bias.zero_()

    def interval_columns(self) -> dict[str, int]:
        """The weights that read the interval input and its column (``log(interval / dt)`` rides after F2 into FC7)."""
        return {"fc7.weight": 2 * 3} if self.interval_input else {}

    def carry_spec(self, batch: int, experts_alone: bool = False, dtype=torch.float32, device=None) -> dict:
        """The GRUs' hidden states, started at their learned ``h0``, and the previous scan's interval."""
        h0 = {"q": self.h0_q, "sigma": self.h0_sigma, "s": self.h0_s}
        return {keys.EXPERT_HIDDEN: {k: v.expand(batch, -1, -1).to(dtype) for k, v in h0.items()},
                keys.PREV_INTERVAL: torch.full((batch,), float(self.dt), dtype=dtype, device=device)}

    def interval_features(self, td, like: torch.Tensor):
        """``(rate_now, rate_before, extra)``: the factors ``dt / interval`` that scale F1 and F3 (1.0 at the
        nominal interval), and the ``log(interval / dt)`` inputs ``[B, M, 1]`` (None without ``interval_input``).
        Writes this scan's interval as the next scan's previous one."""
        interval = td.get(keys.INTERVAL, None)
        prev = td.get(keys.PREV_INTERVAL)
        if interval is None:
            td.set(keys.PREV_INTERVAL, prev.clone())  # unchanged: the nominal interval
            return 1.0, 1.0, like.new_zeros(*like.shape[:2], 1) if self.interval_input else None
        d = interval.to(like.dtype)
        view = (-1, *([1] * (like.dim() - 1)))
        now, before = (self.dt / d).view(view), (self.dt / prev.to(like.dtype)).view(view)
        td.set(keys.PREV_INTERVAL, interval.to(prev.dtype))
        extra = torch.log(d / self.dt).view(-1, 1, 1).expand(*like.shape[:2], 1) if self.interval_input else None
        return now, before, extra

    def features(self, td):
        M = self.n_experts
        z = per_expert(td.get(keys.MEASUREMENT), M)
        has_z = measured(z)
        fused = per_expert(td.get(keys.FUSED), M)
        prior = td.get(keys.EXPERT_PRIOR)
        now, before, extra = self.interval_features(td, prior)
        f1 = torch.where(has_z, z - per_expert(td.get(keys.PREV_MEASUREMENT), M), 0.0)
        f2 = innovation(z, prior)
        f3 = fused - per_expert(td.get(keys.PREV_FUSED), M)
        f4 = fused - td.get(keys.PREV_EXPERT_PRIOR)
        if not isinstance(now, float):  # differences over an interval, as rates at the nominal one
            f1, f3 = f1 * now, f3 * before
        f2 = f2 if extra is None else torch.cat([f2, extra], -1)  # the interval rides with F2 into FC7
        return (
            slog(f1, F1_SCALE), slog(f2, F2_SCALE), slog(f3, self.f3_scale), slog(f4, self.f4_scale)
        )

    def recur(self, td, f1, f2, f3, f4) -> torch.Tensor:
        """One scan of the GRUs and layers on expert-major features ``[M, B, .]`` (``f2`` with whatever rides with
        it into FC7); writes the next hidden states and returns FC2's output ``[M, B, .]``, its first 27 columns the
        gain correction."""
        h = td.get(keys.EXPERT_HIDDEN)
        relu = torch.relu
        h_q = self.gru_q(relu(self.fc5(f4)), h.get("q").transpose(0, 1))
        h_sigma = self.gru_sigma(torch.cat([h_q, relu(self.fc6(f3))], -1), h.get("sigma").transpose(0, 1))
        out_fc1 = relu(self.fc1(h_sigma))
        out_fc7 = relu(self.fc7(torch.cat([f1, f2], -1)))
        h_s = self.gru_s(torch.cat([out_fc1, out_fc7], -1), h.get("s").transpose(0, 1))
        out = self.fc2b(relu(self.fc2a(torch.cat([h_sigma, h_s], -1))))
        out_fc3 = relu(self.fc3(torch.cat([h_s, out[..., : 9 * 3]], -1)))
        h_sigma = relu(self.fc4(torch.cat([h_sigma, out_fc3], -1)))
        hidden = {"q": h_q, "sigma": h_sigma, "s": h_s}
        td.set(keys.EXPERT_HIDDEN, {k: v.transpose(0, 1) for k, v in hidden.items()})
        return out

    def forward(self, td):
        # the layers run expert-major ([M, B, .]): features and hidden states turn once per step
        out_fc2 = self.recur(td, *(f.transpose(0, 1) for f in self.features(td)))
        delta = torch.tanh(out_fc2.transpose(0, 1).unflatten(-1, (9, 3)))
        td.set(keys.EXPERT_GAIN, self.K_ss + self.K_scale * delta)
        return td


class AnalyticGain(Gain):
    """The Kalman gain of each expert from its covariance (ablation; no learned parameters).

    Reads the fused covariance ``P_{t-1|t-1}`` (``("fused", "cov")``), writes each expert's prior
    gain and posterior covariance ``P^(i)_{t|t}`` (Joseph form) to ``("expert", "cov")``; the gain
    takes the fused state's dtype.
    """

    in_keys = [keys.MEASUREMENT, keys.FUSED_COV, keys.FUSED]
    out_keys = [keys.EXPERT_GAIN, keys.EXPERT_COV]

    load_options = ("r",)

    def __init__(self, model_set: ModelSet, dt: float = 1.0, sigma_q: float = 1.0, r: float = 4.0):
        super().__init__(model_set)
        if r <= 0 or sigma_q < 0:
            raise ValueError(f"AnalyticGain needs r > 0 and sigma_q >= 0, got r={r}, sigma_q={sigma_q}")
        self.r, self.dt, self.sigma_q = r, dt, sigma_q
        self.register_buffer("F", model_set.F(dt))
        self.register_buffer("Q", model_set.Q(sigma_q, dt))

    def initial_cov(self, shape, elapsed=None) -> torch.Tensor:
        """Covariance of a starting track: after one scan (``elapsed`` None) ``diag(r^2, 300^2, 10^2)`` per axis;
        after two (differenced velocity over ``elapsed [B]``, the time between the detections)
        ``diag(r^2, 2 r^2 / elapsed^2, 10^2)``."""
        r2 = self.r**2
        d = torch.tensor([r2, 300.0**2, 100.0] * 3, dtype=self.F.dtype, device=self.F.device)
        if elapsed is None:
            return torch.diag(d).expand(*shape, 9, 9).clone()
        d = d.expand(*shape[:1], 9).clone()
        d[:, 1::3] = (2.0 * r2 / elapsed.to(d.dtype) ** 2)[:, None]
        d = d.view(shape[0], *([1] * (len(shape) - 1)), 9).expand(*shape, 9)
        return torch.diag_embed(d).clone()

    def carry_spec(self, batch: int, experts_alone: bool = False, dtype=torch.float32, device=None) -> dict:
        """The fused covariance, a one-scan track's (what a first detection sets)."""
        return {keys.FUSED_COV: self.initial_cov((batch, self.n_experts) if experts_alone else (batch,))}

    def start_carry(self, carry, z: torch.Tensor, x: torch.Tensor, second: bool) -> dict:
        return {keys.FUSED_COV: self.initial_cov(z.shape[:-1], carry.get(keys.START_TIME))} if second else {}

    def forward(self, td):
        P = per_expert(td.get(keys.FUSED_COV), self.n_experts, event_dims=2).to(self.F.dtype)
        interval = td.get(keys.INTERVAL, None)  # this scan's interval per track, where the step carries it
        if interval is None:
            F, Q = self.F, self.Q
        else:
            d = interval.to(P.dtype)
            F = self.model_set.F(d, dtype=P.dtype, device=P.device)  # [B, M, 9, 9]
            Q = self.model_set.Q(self.sigma_q, d, dtype=P.dtype, device=P.device)
        P = F @ P @ F.transpose(-1, -2) + Q
        R = self.r**2 * torch.eye(3, dtype=P.dtype, device=P.device)
        S = P[..., _P, :][..., _P] + R
        K = (inv3(S)[0] @ P[..., _P, :]).transpose(-1, -2)
        has_z = measured(per_expert(td.get(keys.MEASUREMENT), self.n_experts)).unsqueeze(-1)
        K = torch.where(has_z, K, 0.0)
        post = joseph(P, K, P.new_tensor(self.r**2))
        td.set(keys.EXPERT_GAIN, K.to(td.get(keys.FUSED).dtype))
        td.set(keys.EXPERT_COV, post)
        return td
