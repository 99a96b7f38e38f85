"""Experts that are Kalman filters of their own mode, whose process noise KalmanNet learns.

``KalmanNetFilterGain`` is a gain stage in which each expert keeps what an IMM's mode-matched filter
keeps: its own covariance, and its own mode parameter (a CA expert's acceleration, a turn expert's
turn rate ``w``). The gain is the Kalman gain of that covariance, and the KalmanNet network
(architecture 2, as in ``KalmanNetGain``) learns what a filter designer hand-tunes: the process
noise of each scan (large at a maneuver onset, small in steady flight), plus a bounded correction
of the gain. Why: a CA segment's acceleration and a turn's rate are constant, so the best gain on
them falls as the segment goes on (1/n-like), which a covariance recursion does by itself and a
gain network must learn to count; and a turn rate carried as a state of its own is estimated far
better than one implied by a noisy acceleration (docs/immnet.md, "Filter experts").

The augmented state of expert ``i`` is ``y = [x (9), w]``. One scan, per expert:

* input point ``x~``: the previous fused estimate (docs/spec.md section 4), except the expert's own mode
  parameter: a model that carries acceleration (``F[acc, acc] != 0``, CA) keeps its own posterior
  acceleration; an ``AdaptiveTurn`` expert turns at its own rate ``w^(i)`` (bounded by ``_rate_limits``).
  With ``interaction="imm"`` (the recipes'), the IMM's mixed estimate instead (``FilterInteraction``, the step's
  interaction slot);
* prior ``x^(i)_{t|t-1} = f_i(x~, w~)``; covariance ``P- = J (P^(i) + d d^T) J^T + Q^(i)_t``, ``J``
  the Jacobian of ``f_i`` and ``d = x~ - x^(i)_{t-1|t-1}`` the IMM's spread-of-means term for
  having started from the fused estimate rather than the expert's own;
* ``Q^(i)_t = sum_k exp(u_k) Q_k^(i)``: base components (velocity noise horizontal / vertical,
  acceleration noise horizontal / vertical, turn-rate noise), each scaled by the network's bounded
  output ``u = u_max tanh(u_slope raw / u_max)``;
* with ``adapt`` (``immnet.imm.adaptive.AdaptiveNoise``, set at load: ``load_network(adapt=...)``), the
  white-acceleration components (velocity h / v) times the track's ``lambda`` in [1, 100], grown by
  covariance matching on the smallest NIS of the experts
  (docs/immnet.md, "Adaptive process noise");
* ``K = P- H^T (H P- H^T + r^2 I)^-1 + [K_scale tanh(FC2); 0]``; update of ``x``, ``w`` and
  ``P`` (Joseph form, with the gain actually used).

The measurement noise ``r`` is estimated per track from the third differences of the altitude
measurements, which cancel CV and CA motion: ``E[(d^3 z)^2] = 20 r^2``, a running mean started from
a prior of ``r0`` with the weight of ``k0`` samples.
"""

from __future__ import annotations

import math

import torch

from immnet import keys
from immnet.choice import Choice
from immnet.imm.adaptive import AdaptiveNoise
from immnet.data.spec import DataSpec
from immnet.imm.guard import RangeGuard, fresh_share, guarded_transition
from immnet.imm.interaction import enter, mix, mixing_weights, onset_priors, transition_matrix
from immnet.imm.kalman import (
    as_covariance, check_robust, check_vz_std, far, gaussian_loglik, group_loglik, group_maha, huber, inv3, joseph,
    marginal_loglik, quadratic, small_matmul, vertical_speed_prior,
)
from immnet.imm import reacquire as reacq
from immnet.imm.measurement import TOLD, Estimated, Isotropic, PerDetection, ToldStd, measurement_model
from immnet.motion import (
    ACC, N_AUG, POS, POS_VIEW, RATE, TURN_ENTRIES, TURN_RATE_LIMIT_DEG, VEL, ModelSet, ct_jacobian_entries,
    ct_propagate, group_members, measured_groups, Modes, noise_gain,
)
from immnet.stages.base import Stage, measured, per_expert, scan_interval, step_input, track_where
from immnet.stages.features import slog, state_scale
from immnet.stages.gain import Gain, KalmanNetGain
from immnet.stages.layers import StackedLinear
from immnet.stages.predict import Predict
from immnet.stages.update import Update, innovation

N_NOISE = 5  # velocity h / v, acceleration h / v, turn rate
WHITE = (0, 1)  # the white-acceleration components, which AdaptiveNoise's scale multiplies


def _kinds(model_set: ModelSet, dt: float):
    """Per expert: keeps its own acceleration (bool), turns at its own rate (bool), its model's rate range."""
    own_acc, own_rate, lo, hi, nominal = [], [], [], [], []
    for model in model_set:
        rate = bool(model.state_dependent) and hasattr(model, "rate_bounds")
        F = model.F(dt)
        own_rate.append(rate)
        own_acc.append((not rate) and bool(F[2, 2] != 0))
        b = model.rate_bounds() if rate else (0.0, 0.0)
        lo.append(b[0])
        hi.append(b[1])
        nominal.append(model.turn_rate if rate else 0.0)
    return own_acc, own_rate, lo, hi, nominal


def _rate_limits(lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The bounds of each expert's turn rate from its model's range ``[lo, hi]`` (rad/s; 0, 0 for no turn):
    the slow edge as the model's, the fast edge the larger of the model's and ``TURN_RATE_LIMIT_DEG``.
    The model's range is its prior (where its turns start), not what a target can fly: bounded there, a
    faster turn's rate stays below the truth and the expert falls behind the target (docs/robustness.md)."""
    limit = TURN_RATE_LIMIT_DEG * math.pi / 180.0
    return torch.where(lo < 0, lo.clamp(max=-limit), lo), torch.where(hi > 0, hi.clamp(min=limit), hi)


def _register_rate_bounds(stage, model_set: ModelSet, dt: float) -> tuple:
    """Registers on ``stage`` which experts turn at their own rate, ``own_rate``, and the model set's rate range
    ``rate_lo``, ``rate_hi`` (kept in checkpoints), and the bounds derived from it once, ``rate_min``, ``rate_max``
    (``_rate_limits``, float64 so that a ``.double()`` model is exact); returns the experts' ``_kinds``."""
    kinds = _, own_rate, lo, hi, _ = _kinds(model_set, dt)
    stage.register_buffer("own_rate", torch.tensor(own_rate))
    stage.register_buffer("rate_lo", torch.tensor(lo))
    stage.register_buffer("rate_hi", torch.tensor(hi))
    rate_min, rate_max = _rate_limits(torch.tensor(lo, dtype=torch.float64), torch.tensor(hi, dtype=torch.float64))
    stage.register_buffer("rate_min", rate_min, persistent=False)
    stage.register_buffer("rate_max", rate_max, persistent=False)
    return kinds


def _noise_components(own_acc, own_rate, dt, nominal: float | None = None) -> torch.Tensor:
    """Unit process-noise components ``[M, 5, 10, 10]`` (velocity h / v as white acceleration on
    position and velocity, acceleration h / v on a CA expert's acceleration, turn rate on ``w``).

    ``dt`` a float (the nominal interval: the acceleration and turn-rate components are per scan) or a
    tensor ``[B]`` of intervals (``[B, M, 5, 10, 10]``): the white-acceleration components of that interval,
    the random-walk ones (acceleration, turn rate) scaled by ``dt / nominal``, a variance per unit time
    (docs/stages.md, "Any scan interval")."""
    dtype = dt.dtype if isinstance(dt, torch.Tensor) else torch.float64
    G = noise_gain(dt, "white", dtype=dtype, device=dt.device if isinstance(dt, torch.Tensor) else None)  # [..., 9, 3]
    lead = G.shape[:-2]
    walk = 1.0 if nominal is None else (dt / nominal)
    out = torch.zeros(*lead, len(own_acc), N_NOISE, N_AUG, N_AUG, dtype=dtype, device=G.device)
    for i, (acc, rate) in enumerate(zip(own_acc, own_rate)):
        for axis, k in ((0, 0), (1, 0), (2, 1)):
            out[..., i, k, :9, :9] += G[..., :, axis, None] * G[..., None, :, axis]
        if acc:
            for axis, k in ((0, 2), (1, 2), (2, 3)):
                out[..., i, k, ACC[axis], ACC[axis]] = walk
        if rate:
            out[..., i, 4, RATE, RATE] = walk
    return out


def _jacobian_base(model_set: ModelSet, own_rate, dt, dtype=torch.float64, F: torch.Tensor | None = None) -> torch.Tensor:
    """The Jacobian's constant part ``[M, 10, 10]`` (``[B, M, 10, 10]`` for intervals ``dt [B]``): ``F`` for the
    constant models, for a turn expert ``F_CT``'s entries that do not depend on ``w`` (position and the
    vertical CV block, ``w``'s own 1); the rest of a turn expert's Jacobian is written at ``TURN_ENTRIES``
    each scan. ``F``: the model set's ``F(dt)``, where the caller has it."""
    d = torch.as_tensor(dt, dtype=dtype)
    F = model_set.F(d, dtype=dtype, device=d.device) if F is None else F  # [..., M, 9, 9]
    J = F.new_zeros(*F.shape[:-2], N_AUG, N_AUG)
    J[..., :9, :9] = F
    for i, rate in enumerate(own_rate):
        if rate:
            J[..., i, :, :] = 0.0
            for r, c in ((0, 0), (3, 3), (6, 6), (7, 7), (RATE, RATE)):
                J[..., i, r, c] = 1.0
            J[..., i, 6, 7] = d
    return J


def _noise(scale: torch.Tensor, Q_parts: torch.Tensor) -> torch.Tensor:
    """``Q_t = sum_k scale_k Q_k`` ``[B, M, 10, 10]`` from the components' multipliers ``scale [B, M, 5]`` and
    ``Q_parts [M, 5, 10, 10]`` (``[B, M, 5, 10, 10]`` per track's interval): one product over ``k`` per expert."""
    spec = "bmk,mkq->bmq" if Q_parts.dim() == 4 else "bmk,bmkq->bmq"
    return torch.einsum(spec, scale, Q_parts.flatten(-2)).unflatten(-1, Q_parts.shape[-2:])


FREE = "free"
"""``turn_rate="free"``: a turn filter's own rate, not bounded to its model's range (``FilterPredict``)."""


def _check_turn_rate(turn_rate: str | None) -> str | None:
    if turn_rate not in (None, FREE, TOLD):
        raise ValueError(f"turn_rate must be None (each turn filter's own, bounded), {FREE!r} (its own, unbounded) or "
                         f"{TOLD!r} (the truth's, an oracle), got {turn_rate!r}")
    return turn_rate


class Interaction(Choice):
    """Where a filter expert's prediction starts (``FilterInteraction``), the setting ``interaction``: ``FUSED``
    (``"fused"``, the paper's) the previous fused estimate with the expert's own mode parameter; ``IMM``
    (``"imm"``, the recipes') the IMM's mix of the experts' posteriors."""

    FUSED = "fused"
    IMM = "imm"


def _check_restart(restart: str | None, interaction: Interaction, onset: bool) -> str | None:
    if restart not in (None, TOLD):
        raise ValueError(f"restart must be None or {TOLD!r} (the truth's, an oracle), got {restart!r}")
    if restart is not None and not (interaction is Interaction.IMM and onset):
        raise ValueError("restart='data' re-enters the experts with their onset priors: it needs interaction='imm' "
                         "and onset=True")
    return restart


def _check_interaction(interaction: Interaction, p_stay: float, guard=None) -> RangeGuard | None:
    """Checks the interaction's other arguments; returns the guard (``RangeGuard.from_config``)."""
    if not 0.0 < p_stay < 1.0:
        raise ValueError(f"p_stay must be in (0, 1), got {p_stay}")
    guard = RangeGuard.from_config(guard)
    if guard is not None and interaction is not Interaction.IMM:
        raise ValueError("a guard changes the IMM's transition matrix: it needs interaction='imm'")
    return guard


class FilterInteraction(Stage):
    """The interaction of filter experts, a stage of its own: where each expert's prediction starts, its input point
    ``[x~, w~]`` (``("expert", "mixed")`` ``[B, M, 10]``) and covariance (``("expert", "mixed_cov")``).

    ``interaction="fused"`` (the paper's): the previous fused estimate, except the expert's own mode parameter (a CA
    expert's acceleration; a turn expert's rate), with the spread-of-means term ``d d^T`` of having started from
    the fused estimate rather than the expert's own posterior. ``interaction="imm"`` (the recipes'): the IMM's
    mixed estimate, the experts' own posteriors ``[x, w]`` and covariances mixed with
    ``mu_{i|j} = Pi_ij mu_i / sum_k Pi_kj mu_k`` (``mu`` the previous scan's mode probabilities, ``Pi`` with
    ``p_stay`` on the diagonal), where what enters expert ``j`` from an expert ``i != j`` (a switch into ``j``)
    carries the generator's onset prior for what ``j`` keeps of its own: a CA expert's acceleration (mean 0, the
    draw's variance), a turn expert's rate (``+/- 5.5`` deg/s, standard deviation 2.6 deg/s;
    ``immnet.imm.interaction.onset_priors``). Experts alone (stage 1) start from their own posterior either way.

    ``guard`` (``immnet.imm.guard.RangeGuard``, or its fields as a dict; ``True`` for 3D-LAST's)
    makes ``Pi`` state-dependent, per track and source expert, from each expert's previous posterior,
    gives a turn entered at a bound the bound's rate, and writes the transition matrix
    (``("mode", "transition")``) for a Bayesian classifier to predict the modes with, and the share of
    each expert's mixed prior that entered at a speed bound (``("expert", "speed_fresh")``, carried to
    the next scan, where that one-scan turn clears). It holds no weights (its tensors are the model set's and the
    chain's), so a checkpoint is the same with the interaction in this slot or another.
    """

    in_keys = [keys.FUSED, keys.EXPERT_POST, keys.EXPERT_RATE, keys.EXPERT_AUG_COV]
    out_keys = [keys.EXPERT_MIXED, keys.EXPERT_MIXED_COV]

    shared = ("p_stay", "guard", "modes")

    def __init__(self, model_set: ModelSet, dt: float = 1.0, interaction: str = "fused", p_stay: float = 0.995,
                 guard=None, spec: DataSpec | dict | None = None, onset: bool = True, modes: str = "joint",
                 restart: str | None = None):
        """``onset``: the IMM's mix carries the onset priors into each expert (above); False: what enters from
        another expert is that expert's posterior as it is (the textbook IMM's mix, the linear IMMs'). ``modes``:
        modes per group (``IMMNet``'s): each group's coordinates mixed with its own weights (``_mix_groups``).
        ``restart="data"`` (an oracle, with the IMM's mix and its onset priors): where the truth draws its mode's
        parameter anew without a mode switch (a turn's new rate within a turn; the step's input ``("truth",
        "restart")`` ``[B]``), every expert enters from its mix with its onset prior too (``immnet.imm.runner.run``'s
        ``restart``: the switch-clairvoyant reference)."""
        super().__init__(model_set)
        self.interaction = interaction = Interaction.parse(interaction)
        self.restart = _check_restart(restart, interaction, onset)
        if restart is not None:
            self.in_keys = [*self.in_keys, keys.TRUE_RESTART]
        self.dt = dt
        self.onset = bool(onset)
        groups = Modes.parse(modes).groups
        members = [] if groups is None else group_members(groups)
        self.n_groups = len(members)
        for a, coords in enumerate(members):  # each group's coordinates of [x, w]
            self.register_buffer(f"group_{a}", torch.tensor(coords), persistent=False)
        spec = spec if isinstance(spec, DataSpec) else DataSpec.from_dict(spec)  # the onset priors' statistics
        self.guard = _check_interaction(interaction, p_stay, guard)
        self.p_stay = float(p_stay)
        if interaction is Interaction.IMM:  # the mix reads the previous scan's mode probabilities and writes
            self.in_keys = [*self.in_keys, keys.EXPERT_PROBS]  # the transition it mixed with, for the mode update
            self.out_keys = [*self.out_keys, keys.MODE_TRANSITION]  # (one p_stay)
        if self.guard is not None:  # and the speed-bound shares it carries
            self.in_keys = [*self.in_keys, keys.GUARD_FRESH]
            self.out_keys = [*self.out_keys, keys.GUARD_FRESH]
        own_acc, own_rate, _, _, nominal = _kinds(model_set, dt)
        M = len(model_set)
        f64 = torch.float64  # float64, so that a .double() model is exact
        self.register_buffer("Pi", transition_matrix(p_stay, M), persistent=False)
        keep, mean, cov = onset_priors(own_acc, own_rate, nominal, acc_var=spec.ca_acc_var(),
                                       rate_prior_deg=spec.turn_rate_prior_deg())
        self.register_buffer("mix_keep", keep, persistent=False)
        self.register_buffer("mix_mean", mean, persistent=False)
        self.register_buffer("mix_cov", cov, persistent=False)
        acc_mask = torch.zeros(M, 9, dtype=torch.bool)
        acc_mask[:, list(ACC)] = torch.tensor(own_acc)[:, None]
        self.register_buffer("own_acc_mask", acc_mask, persistent=False)
        modes = model_set.modes
        self.register_buffer("data_modes", modes, persistent=False)
        bound_sign = torch.where(modes == 2, 1.0, torch.where(modes == 3, -1.0, 0.0)) * torch.tensor(own_rate, dtype=f64)
        self.register_buffer("bound_sign", bound_sign, persistent=False)  # a bound turn's rate sign per expert (0: none)

    def for_experts_alone(self) -> "FilterInteraction":
        """Experts alone start from their own posterior with either interaction: no mix, no guard."""
        if self.interaction is Interaction.FUSED:
            return self
        return FilterInteraction(self.model_set, self.dt, Interaction.FUSED, self.p_stay)

    def carry_spec(self, batch: int, experts_alone: bool = False, dtype=torch.float32, device=None) -> dict:
        """The guard's speed-bound shares (none entered yet)."""
        if self.guard is None or experts_alone:
            return {}
        return {keys.GUARD_FRESH: torch.zeros(batch, self.n_experts, dtype=dtype, device=device)}

    def _mix(self, td):
        """The IMM's mixed estimate of each expert ``[B, M, 10]`` and its covariance ``[B, M, 10, 10]``."""
        y = torch.cat([td.get(keys.EXPERT_POST), td.get(keys.EXPERT_RATE).unsqueeze(-1)], -1)  # [B, i, 10]
        P = td.get(keys.EXPERT_AUG_COV)
        mu = td.get(keys.EXPERT_PROBS)
        Pi = self.Pi.to(y.dtype)
        if self.guard is not None:  # per track and source expert [B, i, j]; a prior: no gradient flows through it
            with torch.no_grad():
                Pi, share, speed_share = guarded_transition(
                    Pi, self.guard.events(y[..., :9], y[..., RATE], scan_interval(td, self.dt)[0]), self.data_modes,
                    td.get(keys.GUARD_FRESH, None))
            share = share * (self.bound_sign != 0).to(share.dtype)
        # the transition the experts are mixed with is the one the mode update predicts with
        td.set(keys.MODE_TRANSITION, Pi if Pi.dim() == 3 else Pi.expand(mu.shape[0], *Pi.shape))
        w = mixing_weights(mu, Pi if mu.dim() == 2 else Pi.unsqueeze(-3))  # mu_{i|j} [B, i, j] (per group [B, G, i, j])
        if mu.dim() == 3:  # modes per group (the guard is refused with them): each group's IMM mixes its own block
            return self._mix_groups(w, y, P)
        bound = None
        if self.guard is not None:  # a turn entered (or re-entered) at a range bound has the bound's rate
            td.set(keys.GUARD_FRESH, fresh_share(w.detach(), speed_share))
            rate = self.bound_sign.to(y.dtype) * (self.guard.rate_deg * math.pi / 180.0)
            bound = (share, rate, (self.guard.rate_std_deg * math.pi / 180.0) ** 2, RATE)
        return mix(w, y, P, (self.mix_keep, self.mix_mean, self.mix_cov) if self.onset else None, bound)

    def _mix_groups(self, w: torch.Tensor, y: torch.Tensor, P: torch.Tensor):
        """The mix with modes per group, weights ``w [B, G, i, j]``: each group's coordinates of ``[x, w]`` and its
        block of the covariance from the mix of those coordinates with that group's weights (``mix``, which treats
        each coordinate and each entry apart: the block of the whole mix), the blocks across groups 0."""
        x0, P0 = torch.zeros_like(y), torch.zeros_like(P)
        for a in range(self.n_groups):
            idx = self.get_buffer(f"group_{a}")
            priors = None
            if self.onset:
                priors = (self.mix_keep[:, idx], self.mix_mean[:, idx], self.mix_cov[:, idx[:, None], idx])
            xa, Pa = mix(w[:, a], y.index_select(-1, idx), P.index_select(-2, idx).index_select(-1, idx), priors)
            x0.index_copy_(-1, idx, xa)
            P0[..., idx[:, None], idx] = Pa
        return x0, P0

    def forward(self, td):
        own = td.get(keys.EXPERT_POST)
        if self.interaction is Interaction.IMM and td.get(keys.FUSED).dim() == 2:  # not experts alone
            y0, P0 = self._mix(td)
            if self.restart is not None:  # the truth's new draw within a mode: every expert enters with its prior
                again = step_input(td, keys.TRUE_RESTART).to(torch.bool)
                ye, Pe = enter(y0, P0, self.mix_keep, self.mix_mean, self.mix_cov)
                y0, P0 = track_where(again, ye, y0), track_where(again, Pe, P0)
        else:
            x = torch.where(self.own_acc_mask, own, per_expert(td.get(keys.FUSED), self.n_experts))
            y0 = torch.cat([x, td.get(keys.EXPERT_RATE).unsqueeze(-1)], -1)
            d = torch.cat([x - own, torch.zeros_like(x[..., :1])], -1)
            P0 = td.get(keys.EXPERT_AUG_COV) + d.unsqueeze(-1) * d.unsqueeze(-2)
        td.set(keys.EXPERT_MIXED, y0)
        td.set(keys.EXPERT_MIXED_COV, P0)
        return td


class FilterPredict(Predict):
    """Predict for filter experts, from the interaction's input point ``[x~, w~]`` and covariance
    (``FilterInteraction``): the prior mean ``f_i(x~, w~)`` (the turn rate bounded to the expert's range, zero for
    an expert without one) and the prior covariance before process noise, ``J P~ J^T``, ``J`` the Jacobian of
    ``f_i`` (the gain adds the process noise).

    ``turn_rate`` (the gain's, ``FilterGain(turn_rate=...)``): None, the turn filters' own rate, bounded to their
    model's range (``_rate_limits``); ``"free"``, their own rate unbounded (an extended Kalman filter of ``[x, w]`` as
    it is: the switch-clairvoyant reference); ``"data"``, the truth's rate of each scan (the step's input
    ``("truth", "turn_rate")`` ``[B]``, rad/s, either sign) in place of their own, held as known (its variance and
    covariances 0): the clairvoyant bound's turn at the true rate (an oracle)."""

    in_keys = [keys.EXPERT_MIXED, keys.EXPERT_MIXED_COV]
    out_keys = [keys.EXPERT_PRIOR, keys.EXPERT_RATE, keys.EXPERT_AUG_PRIOR_COV]

    def __init__(self, model_set: ModelSet, dt: float = 1.0, turn_rate: str | None = None):
        super().__init__(model_set, dt)
        self.turn_rate = _check_turn_rate(turn_rate)
        if self.turn_rate == TOLD:
            self.in_keys = [*self.in_keys, keys.TRUE_TURN_RATE]
        own_acc, own_rate, _, _, _ = _register_rate_bounds(self, model_set, dt)
        self.register_buffer("own_acc", torch.tensor(own_acc))  # the model set's, kept with the weights
        # a told rate is known: the turn filters' rate row and column of the covariance [M, N_AUG], built once
        self.register_buffer("rate_known", self.own_rate[:, None] & (torch.arange(N_AUG) == RATE), persistent=False)
        self.has_turn = any(own_rate)  # a python bool: no data-dependent branch in a compiled step
        self._own_rate = own_rate
        self.register_buffer("J_base", _jacobian_base(model_set, own_rate, dt), persistent=False)
        self.register_buffer("turn_index", torch.tensor([r * N_AUG + c for r, c in TURN_ENTRIES]), persistent=False)

    def forward(self, td):
        M = self.n_experts
        y0, P0 = td.get(keys.EXPERT_MIXED), td.get(keys.EXPERT_MIXED_COV)
        x, w = y0[..., :9], y0[..., RATE]
        if self.turn_rate == TOLD:  # the truth's rate, known: no variance, no covariance with the state
            w = step_input(td, keys.TRUE_TURN_RATE).to(w.dtype).unsqueeze(-1).expand_as(w)
            P0 = P0.masked_fill(self.rate_known.unsqueeze(-1) | self.rate_known.unsqueeze(-2), 0.0)
        elif self.turn_rate is None:
            w = torch.clamp(w, self.rate_min.to(w.dtype), self.rate_max.to(w.dtype))
        w = torch.where(self.own_rate, w, torch.zeros_like(w))
        dt, per_track = scan_interval(td, self.dt)
        if per_track:  # this scan's interval per track: F and the Jacobian's constant part of it
            d = dt[:, 0].to(x.dtype)
            F = self.model_set.F(d, dtype=x.dtype, device=x.device)  # [B, M, 9, 9]
            prior = torch.einsum("bmij,bmj->bmi", F, x)
            J = _jacobian_base(self.model_set, self._own_rate, d, x.dtype, F)
            dt = dt.to(x.dtype)
        else:  # F from the Jacobian's constant part, built in float64 (a linear turn's sin and cos exact in a .double())
            J = self.J_base.to(x.dtype).expand(x.shape[0], M, N_AUG, N_AUG)
            prior = torch.einsum("mij,bmj->bmi", self.J_base[:, :9, :9].to(x.dtype), x)
        if self.has_turn:
            turned = ct_propagate(x, w, dt)
            prior = torch.where(self.own_rate[:, None], turned, prior)
            entries = ct_jacobian_entries(x, w, dt) * self.own_rate.to(x.dtype)[:, None]  # [B, M, 18]
            scattered = entries.new_zeros(*entries.shape[:2], N_AUG * N_AUG).index_copy(-1, self.turn_index, entries)
            J = J + scattered.view(*entries.shape[:2], N_AUG, N_AUG)
        td.set(keys.EXPERT_PRIOR, prior)
        td.set(keys.EXPERT_RATE, w)
        td.set(keys.EXPERT_AUG_PRIOR_COV, J @ P0 @ J.transpose(-1, -2))
        return td


class FilterUpdate(Update):
    """Update for filter experts: the state as ``Update``, then the turn rate ``w`` (bounded to the
    expert's range) and the augmented covariance (Joseph form, with the gain actually used)."""

    in_keys = [
        keys.MEASUREMENT, keys.EXPERT_PRIOR, keys.EXPERT_GAIN,
        keys.EXPERT_RATE, keys.EXPERT_RATE_GAIN, keys.EXPERT_AUG_PRIOR_COV, keys.NOISE_VAR,
    ]
    out_keys = [keys.EXPERT_POST, keys.EXPERT_RATE, keys.EXPERT_AUG_COV]

    def __init__(self, model_set: ModelSet, dt: float = 1.0, correction: bool = False, turn_rate: str | None = None,
                 told_cov: bool = False, robust: bool = False):
        """``told_cov``: the carried measurement noise ``("memory", "r2")`` is each detection's covariance ``[B, 3, 3]``
        (``FilterGain(r="detection")``), not a variance ``[B]``. ``robust``: the gain is Huber's robust one (``FilterGain(
        robust=k)``), ``K' = w K`` with its weight ``("expert", "robust_weight")``, whose covariance is Joseph's with
        ``R' = R + (1 / w - 1) S`` (``immnet.imm.kalman``'s module doc: ``P - w K H P``). ``correction``: add the gain's learned state correction (``("expert", "correction")``,
        ``KalmanNetFilterGain(state_correction=...)``) to each expert's posterior mean; the covariance is the
        filter's (the correction enters as a known input). ``turn_rate``: ``FilterPredict``'s; bounded to the
        model's range where None, else kept as it is."""
        super().__init__(model_set)
        self.turn_rate = _check_turn_rate(turn_rate)
        _register_rate_bounds(self, model_set, dt)
        self.correction = bool(correction)
        self.told_cov = bool(told_cov)
        self.robust = bool(robust)
        if self.robust:
            self.in_keys = [*self.in_keys, keys.EXPERT_ROBUST_WEIGHT]
        if self.correction:
            self.in_keys = [*self.in_keys, keys.EXPERT_CORRECTION]

    def forward(self, td):
        td = super().forward(td)  # the state
        if self.correction:
            td.set(keys.EXPERT_POST, td.get(keys.EXPERT_POST) + td.get(keys.EXPERT_CORRECTION))
        nu = innovation(td.get(keys.MEASUREMENT), td.get(keys.EXPERT_PRIOR))
        w = td.get(keys.EXPERT_RATE) + (td.get(keys.EXPERT_RATE_GAIN) * nu).sum(-1)
        if self.turn_rate is None:
            w = torch.where(self.own_rate, torch.clamp(w, self.rate_min.to(w.dtype), self.rate_max.to(w.dtype)), w)
        K = torch.cat([td.get(keys.EXPERT_GAIN), td.get(keys.EXPERT_RATE_GAIN).unsqueeze(-2)], -2)  # [B, M, 10, 3]
        P = td.get(keys.EXPERT_AUG_PRIOR_COV)
        r2 = noise_matrix(td.get(keys.NOISE_VAR), P.shape[1], self.told_cov)
        if self.robust:  # R' = R + (1 / w - 1) S; per coordinate (modes per group) R + D S D, D = diag(sqrt(1/w - 1))
            weight = td.get(keys.EXPERT_ROBUST_WEIGHT).to(P.dtype)
            r2 = as_covariance(r2.to(P.dtype), P)
            if weight.dim() == 3:
                D = _inflation(weight)
                r2 = r2 + D[..., :, None] * innovation_cov(P, r2) * D[..., None, :]
            else:
                r2 = r2 + (1.0 / weight[..., None, None] - 1.0) * innovation_cov(P, r2)
        td.set(keys.EXPERT_RATE, w)
        td.set(keys.EXPERT_AUG_COV, joseph(P, K, r2))
        return td


def _inflation(w: torch.Tensor) -> torch.Tensor:
    """``sqrt(1 / w - 1)`` of Huber's weights ``w`` in (0, 1] (``R' = R + D S D``), 0 where ``w = 1`` with a finite
    gradient there (no ``sqrt(0)`` in the graph)."""
    below = w < 1.0
    return torch.where(below, torch.sqrt(torch.where(below, 1.0 / w - 1.0, torch.ones_like(w))), torch.zeros_like(w))


def innovation_cov(P: torch.Tensor, r2: torch.Tensor) -> torch.Tensor:
    """``S = H P H^T + R`` of a prior covariance ``P [..., 9 or 10, 9 or 10]`` (its positions' block, ``POS``) and
    the measurement noise ``r2``: a variance broadcasting as ``[..., 1, 1]`` (``R = r^2 I``) or a covariance
    ``[..., 3, 3]`` (``noise_matrix``)."""
    return P[..., POS_VIEW, POS_VIEW] + as_covariance(r2, P)


def noise_matrix(noise: torch.Tensor, n_experts: int, told_cov: bool) -> torch.Tensor:
    """The carried measurement noise ``("memory", "r2")`` per expert, as ``innovation_cov`` takes it: a variance
    ``[B]`` / ``[B, M]`` as ``[B, M, 1, 1]``, or (``told_cov``) a covariance ``[B, 3, 3]`` / ``[B, M, 3, 3]`` as
    ``[B, M, 3, 3]``."""
    if told_cov:
        return per_expert(noise, n_experts, event_dims=2)
    return per_expert(noise, n_experts, event_dims=0)[..., None, None]


class _FilterExperts:
    """What every filter-expert gain shares: the measurement-noise estimate, the carry of a starting
    track, the base process noise, and the Kalman gain and log-likelihood of a prior covariance.
    Mixed into a ``Gain`` (``FilterGain``) or a ``KalmanNetGain`` (``KalmanNetFilterGain``)."""

    shared = ("p_stay", "guard", "modes")
    load_options = ("guard", "adapt", "r", "reacquire", "robust", "start_vz_std")
    state_correction = None
    """The bounds of ``KalmanNetFilterGain``'s learned state correction, None without one
    (``FilterUpdate(correction=...)``)."""

    @property
    def per_detection(self) -> bool:
        """Whether the experts are told each detection's covariance (``r="detection"``, ``PerDetection``)."""
        return isinstance(self.measurement, PerDetection)

    def stages(self, model_set: ModelSet, dt: float) -> tuple[FilterInteraction, FilterPredict, FilterUpdate]:
        """The interaction, predict and update these experts need (``Gain.stages``): the interaction with this gain's
        ``interaction``, ``p_stay`` and ``guard``, the predict with its ``turn_rate``, the update with its
        ``turn_rate``, measurement model, robust update and state correction (``FilterUpdate``)."""
        return (FilterInteraction(model_set, dt, self.interaction, self.p_stay, self.guard, self.spec, self.onset,
                                  self.modes, self.restart),
                FilterPredict(model_set, dt, turn_rate=self.turn_rate),
                FilterUpdate(model_set, dt, correction=self.state_correction is not None, turn_rate=self.turn_rate,
                             told_cov=self.per_detection, robust=self.robust is not None))

    def _init_filter(self, model_set: ModelSet, dt: float = 1.0, *,
                     noise_std: tuple[float, float, float, float, float] = (0.2, 0.2, 0.01, 0.002, 1e-5),
                     r0: float = 4.0, k0: float = 3.0, rate_std0_deg: float = 5.0, interaction: str = "fused",
                     p_stay: float = 0.995, guard: bool | dict | None = None, adapt: bool | dict | None = None,
                     r: float | str | None = None, spec: DataSpec | dict | None = None, onset: bool = True,
                     model_noise: float | list[float] | None = None,
                     start_acc_std: float | list[float | None] | None = None, modes: str = "joint",
                     turn_rate: str | None = None, restart: str | None = None, robust: float | None = None,
                     reacquire: dict | bool | None = None, start_vz_std: float | None = None):
        """The filter experts' options, the keyword arguments of ``FilterGain`` and ``KalmanNetFilterGain`` (one
        signature for both). ``noise_std``: base standard deviations of the five process-noise components (velocity h
        / v in m/s^2 of white acceleration, acceleration h / v in m/s^2 per scan, turn rate in rad/s per scan);
        ``r0``, ``k0``: the prior of the measurement-noise estimate; ``rate_std0_deg``: a turn filter's start std of
        its rate; ``interaction``, ``p_stay``, ``guard``, ``onset``, ``restart``: ``FilterInteraction``'s (``onset``:
        its onset priors; ``restart="data"``: its oracle restart); ``adapt``: adaptive process noise
        (``AdaptiveNoise.from_config``; off by default); ``r``: the measurement model (``measurement_model``: a
        number, ``"data"``, ``"detection"``, None estimated). ``reacquire``: re-acquisition
        (``immnet.imm.reacquire.Reacquire``'s fields as a dict, True its defaults, None off; the model-based IMMs'
        ``reacquire``): a track whose run of detections far from every expert agrees restarts at the last of them as
        at its first detection (``IMMNet.scan``); experts alone (stage 1) run without it. ``robust``: Huber's ``k`` of
        each expert's update (``immnet.imm.kalman``'s module doc: the gain ``w K``, ``w = min(1, k / d)`` of the
        innovation's Mahalanobis distance ``d``, the likelihood Huber's; the model-based IMMs' ``robust``), None: the
        plain update. ``model_noise``: each motion model's own process noise ``Q(sigma_q_i, dt)`` (one ``sigma_q``
        for all models or one per model) in place of the ``noise_std`` components; ``start_acc_std``: the start
        covariance's acceleration standard deviation on every axis (None: the CA draw's), one for every expert or one
        per expert; ``start_vz_std``: a prior on the vertical speed at a track's start, ``N(0, start_vz_std^2)`` m/s
        fused with the start's (the model-based IMMs' ``vz_std``), None: none. They make the linear IMMs' filters
        (docs/core.md). ``modes``: modes per group (``IMMNet``'s, set there once): the experts' likelihood per group
        (``group_loglik``), ``("expert", "loglik")`` ``[B, G, M]``. ``turn_rate``: the turn filters' rate, their own
        bounded to the model's range (None), their own unbounded (``"free"``) or the truth's of each scan, the step's
        input ``("truth", "turn_rate")`` (``"data"``, an oracle: the clairvoyant bound's configuration;
        ``FilterPredict``)."""
        self.interaction = interaction = Interaction.parse(interaction)
        self.start_vz_std = check_vz_std(start_vz_std)
        self.guard = _check_interaction(interaction, p_stay, guard)
        self.turn_rate = _check_turn_rate(turn_rate)
        self.restart = _check_restart(restart, interaction, onset)  # the interaction's
        self.modes = Modes.parse(modes)
        groups = self.modes.groups
        self.z_groups = None if groups is None else measured_groups(groups)  # each group's measured coordinates
        if groups is not None and self.guard is not None:
            raise ValueError(f"modes per group (modes={self.modes.value!r}) and the range guard do not go together: the "
                             "guard's transition is one per track and expert, from the whole state")
        self.robust = check_robust(robust)
        # each measured coordinate's group (modes per group: the robust update weighs each group's innovation)
        self.coordinate_group = None if groups is None else [
            next(g for g, members in enumerate(self.z_groups) if i in members) for i in range(3)]
        if self.robust is not None:
            self.in_keys = [*self.in_keys, keys.ROBUST_SPARE]
            self.out_keys = [*self.out_keys, keys.EXPERT_ROBUST_WEIGHT, keys.ROBUST_SPARE]
        self.reacquire = reacq.Reacquire.from_config(reacquire)
        if self.reacquire is not None:
            if groups is not None:
                raise ValueError(f"re-acquisition reads the whole innovation: it takes modes 'joint', got "
                                 f"modes={self.modes.value!r}")
            self.in_keys = [*self.in_keys, *REACQUIRE_CARRY]
            self.out_keys = [*self.out_keys, *REACQUIRE_CARRY, keys.REACQUIRE]
        self.onset = bool(onset)
        if model_noise is not None:  # each motion model's own Q(sigma_q_i, dt), as the linear IMMs'
            sq = model_noise if isinstance(model_noise, (list, tuple)) else [model_noise] * len(model_set)
            if len(sq) != len(model_set) or not all(math.isfinite(float(v)) and float(v) >= 0 for v in sq):
                raise ValueError(f"model_noise needs one sigma_q >= 0 per model ({len(model_set)}) or one for all, "
                                 f"got {model_noise!r}")
            model_noise = [float(v) for v in sq]
        self.model_noise = model_noise
        stds = start_acc_std if isinstance(start_acc_std, (list, tuple)) else [start_acc_std] * len(model_set)
        if len(stds) != len(model_set) or not all(v is None or (math.isfinite(v) and v >= 0) for v in stds):
            raise ValueError(f"start_acc_std must be finite and >= 0 or None (the CA draw's), one for every model or one "
                             f"per model ({len(model_set)}), got {start_acc_std!r}")
        stds = [None if v is None else float(v) for v in stds]  # per expert
        self.spec = spec if isinstance(spec, DataSpec) else DataSpec.from_dict(spec)  # the start's CA prior
        self.measurement = measurement_model(r, (Isotropic, ToldStd, PerDetection, Estimated))
        # the step's input (r [B] or meas_cov [B, 3, 3]) and, per detection, the carried covariance (a missed scan's)
        self.in_keys = [*self.in_keys, *self.measurement.needs, *((keys.NOISE_VAR,) if self.per_detection else ())]
        self.adapt = AdaptiveNoise.from_config(adapt)
        if self.adapt is not None:  # the track's log lambda is carried
            self.in_keys = [*self.in_keys, keys.Q_SCALE]
            self.out_keys = [*self.out_keys, keys.Q_SCALE]
        self.register_buffer("white_mask", torch.isin(torch.arange(N_NOISE), torch.tensor(WHITE)), persistent=False)
        self.p_stay = float(p_stay)
        if not (r0 > 0 and k0 > 0 and rate_std0_deg >= 0 and math.isfinite(r0 + k0 + rate_std0_deg)):
            raise ValueError(f"r0 and k0 must be > 0 and rate_std0_deg >= 0, got {r0}, {k0}, {rate_std0_deg}")
        if len(noise_std) != N_NOISE or not all(math.isfinite(v) and v >= 0 for v in noise_std):
            raise ValueError(f"noise_std needs {N_NOISE} standard deviations >= 0, got {noise_std}")
        own_acc, own_rate, lo, hi, nominal = _kinds(model_set, dt)
        std = torch.tensor(noise_std, dtype=torch.float64)
        if self.model_noise is None:
            parts = _noise_components(own_acc, own_rate, dt) * std.square()[None, :, None, None]
        else:
            parts = self._model_noise_parts(dt)
        self.register_buffer("Q_parts", parts)
        self.register_buffer("noise_var_std", std.square(), persistent=False)
        self._own_acc, self._own_rate = own_acc, own_rate
        self.register_buffer("rate_nominal", torch.tensor(nominal))
        self.register_buffer("own_rate", torch.tensor(own_rate))
        self.register_buffer("acc_var0", torch.tensor(self.spec.ca_acc_var(), dtype=torch.float64))
        # a starting track's acceleration variance per expert and axis [M, 3]: start_acc_std^2 where set, else the
        # CA draw's
        self.register_buffer("start_acc_var", torch.stack(
            [self.acc_var0 if v is None else torch.full((3,), v * v, dtype=torch.float64) for v in stds]),
            persistent=False)
        self.r0, self.k0, self.dt = float(r0), float(k0), dt
        self.rate_var0 = float((rate_std0_deg * math.pi / 180.0) ** 2)

    def _model_noise_parts(self, dt) -> torch.Tensor:
        """With ``model_noise``: the motion models' own ``Q(sigma_q_i, dt)`` as the first noise component (the
        state block of ``[x, w]``), the others zero: ``[M, 5, 10, 10]``, ``[B, M, 5, 10, 10]`` for ``dt [B]``."""
        dtype = dt.dtype if isinstance(dt, torch.Tensor) else torch.float64
        Q = self.model_set.Q(self.model_noise, dt, dtype=dtype, device=dt.device if isinstance(dt, torch.Tensor) else None)
        out = Q.new_zeros(*Q.shape[:-2], N_NOISE, N_AUG, N_AUG)
        out[..., 0, :9, :9] = Q
        return out

    def q_parts(self, td, like: torch.Tensor) -> torch.Tensor:
        """The base noise components of this scan: ``Q_parts [M, 5, 10, 10]`` at the nominal interval, or
        ``[B, M, 5, 10, 10]`` for the step's interval per track (``_noise_components``, or the models' ``Q``)."""
        dt, per_track = scan_interval(td, self.dt)
        if not per_track:
            return self.Q_parts.to(like.dtype)
        if self.model_noise is not None:
            return self._model_noise_parts(dt[:, 0].to(like.dtype))
        parts = _noise_components(self._own_acc, self._own_rate, dt[:, 0].to(like.dtype), self.dt)
        return parts * self.noise_var_std.to(like.dtype)[:, None, None]

    # --- the measurement noise --------------------------------------------------------------
    def noise_var(self, total: torch.Tensor, count: torch.Tensor, td=None) -> torch.Tensor:
        """``r^2`` per track: the running mean ``(k0 r0^2 + total) / (k0 + count)`` of the third-difference
        samples, the fixed ``r^2`` where ``r`` was given, or the square of the step's input ``r`` (``td``'s ``"r"``
        ``[B]``) where ``r`` is told per track (``"data"``)."""
        if isinstance(self.measurement, ToldStd):
            told = step_input(td, keys.R).to(total.dtype).reshape(-1, *([1] * (total.dim() - 1)))
            return (told * told).expand_as(total)
        if self.per_detection:
            return self._told_cov(td)
        if isinstance(self.measurement, Isotropic):
            return torch.full_like(total, self.measurement.r**2)
        return (self.k0 * self.r0**2 + total) / (self.k0 + count)

    def _told_cov(self, td, z: torch.Tensor | None = None) -> torch.Tensor:
        """Each detection's covariance ``[B, 3, 3]`` (experts alone ``[B, M, 3, 3]``), the step's input ``"meas_cov"``,
        where the scan has a detection (and its covariance is finite); elsewhere the carried one (the last detection's),
        which a missed scan's update does not read. ``z``: the scan's measurement (None: ``td``'s)."""
        prev = td.get(keys.NOISE_VAR)
        R = step_input(td, keys.MEAS_COV).to(prev.dtype)
        if R.dim() < prev.dim():  # experts alone: one detection for every expert
            R = R.unsqueeze(1).expand_as(prev)
        z = td.get(keys.MEASUREMENT) if z is None else z
        ok = measured(z)[..., None] & torch.isfinite(R).flatten(-2).all(-1)[..., None, None]
        return torch.where(ok, R, prev)

    def noise(self, td):
        """Push ``z_t`` into the history; the running estimate of ``r^2`` from altitude third differences."""
        z = td.get(keys.MEASUREMENT)
        hist = td.get(keys.Z_HISTORY)  # [..., 3, 3]: z_{t-1}, z_{t-2}, z_{t-3} (NaN = none)
        gaps = td.get(keys.INTERVAL_HISTORY)  # [..., 2]: the intervals z_{t-2} -> z_{t-1} and z_{t-3} -> z_{t-2}
        dt, per_track = scan_interval(td, self.dt)
        if per_track:  # a third divided difference at the scans' times cancels CV and CA motion at any spacing
            d = dt.view(-1, *([1] * (z.dim() - 1))).to(z.dtype)  # [B, 1] or [B, 1, 1]
            s1 = (-d[..., 0]).expand_as(gaps[..., 0])
            s2 = s1 - gaps[..., 0]
            s3 = s2 - gaps[..., 1]
            s = torch.stack([torch.zeros_like(s1), s1, s2, s3], -1)  # [..., 4]
            diff = s.unsqueeze(-1) - s.unsqueeze(-2) + torch.eye(4, dtype=s.dtype, device=s.device)
            c = 1.0 / diff.prod(-1)  # divided-difference weights, up to a common factor
            alt = torch.stack([z[..., 2], hist[..., 0, 2], hist[..., 1, 2], hist[..., 2, 2]], -1)
            d3 = (c * alt).sum(-1)
            sample = d3 * d3 / (c * c).sum(-1)  # E = r^2, as (d^3 z)^2 / 20 at equal spacing
            td.set(keys.INTERVAL_HISTORY, torch.stack([d[..., 0].expand_as(s1), gaps[..., 0]], -1))
        else:
            d3 = z[..., 2] - 3.0 * hist[..., 0, 2] + 3.0 * hist[..., 1, 2] - hist[..., 2, 2]
            sample = d3 * d3 / 20.0
            td.set(keys.INTERVAL_HISTORY, gaps.clone())  # unchanged: the nominal intervals
        ok = torch.isfinite(d3)
        total = td.get(keys.NOISE_SUM) + torch.where(ok, sample, 0.0)
        count = td.get(keys.NOISE_COUNT) + ok.to(total.dtype)
        td.set(keys.NOISE_SUM, total)
        td.set(keys.NOISE_COUNT, count)
        td.set(keys.Z_HISTORY, torch.cat([z.unsqueeze(-2), hist[..., :2, :]], -2))
        r2 = self.noise_var(total, count, td)
        td.set(keys.NOISE_VAR, r2)
        return r2

    # --- a starting track ---------------------------------------------------------------------
    def carry_spec(self, batch: int, experts_alone: bool = False, dtype=torch.float32, device=None) -> dict:
        """What the gain it is mixed into carries (KalmanNet's hidden states), the gain's own part for tracks that have
        not started (``[B]``, or ``[B, M]`` per expert experts alone), and the robust update's spare and
        re-acquisition's watch where it has them (not experts alone)."""
        M = self.n_experts
        shape = (batch, M) if experts_alone else (batch,)
        adapt = {} if self.adapt is None else {keys.Q_SCALE: torch.zeros(shape, dtype=dtype, device=device)}
        r2 = (self.measurement.r if isinstance(self.measurement, Isotropic) else self.r0) ** 2
        noise = torch.full(shape, r2, dtype=dtype, device=device)
        if self.per_detection:  # a covariance per detection: r0^2 I until the track's first detection
            noise = noise[..., None, None] * torch.eye(3, dtype=dtype, device=device)
        spec = super().carry_spec(batch, experts_alone, dtype, device) | adapt | {
            keys.EXPERT_POST: torch.zeros(batch, M, 9, dtype=dtype, device=device),
            keys.EXPERT_RATE: self.rate_nominal.to(dtype).expand(batch, M).clone(),
            keys.EXPERT_AUG_COV: self.start_cov(batch, torch.full((batch, M), r2, dtype=dtype, device=device), False),
            keys.NOISE_VAR: noise,
            keys.NOISE_SUM: torch.zeros(shape, dtype=dtype, device=device),
            keys.NOISE_COUNT: torch.zeros(shape, dtype=dtype, device=device),
            keys.Z_HISTORY: torch.full((*shape, 3, 3), float("nan"), dtype=dtype, device=device),
            keys.INTERVAL_HISTORY: torch.full((*shape, 2), float(self.dt), dtype=dtype, device=device),
        }
        if experts_alone:
            return spec
        if self.robust is not None:  # one per group with modes per group
            spec = spec | {keys.ROBUST_SPARE: torch.zeros(self._spare_shape(batch), dtype=dtype, device=device)}
        if self.reacquire is None:
            return spec
        return spec | dict(zip(REACQUIRE_CARRY, reacq.watch(batch, dtype, device)))

    def start_carry(self, carry, z: torch.Tensor, x: torch.Tensor, second: bool) -> dict:
        """The gain's carry after a track's first or second detection ``z`` (``x``: ``start_estimate``'s) with what
        the gain it is mixed into sets, no far plot before it (the robust update's), and a watch that waits for the
        detection confirming it (re-acquisition's)."""
        M = self.n_experts
        B = z.shape[0]
        hist = carry.get(keys.Z_HISTORY)
        nan = prev = torch.full_like(z, float("nan"))
        if second:  # the first detection is the previous scan's only where no scan was missed between
            adjacent = (carry.get(keys.START_SCANS) == 1).view(-1, *([1] * (z.dim() - 1)))
            prev = torch.where(adjacent, hist[..., 0, :], float("nan"))
        elapsed = carry.get(keys.START_TIME)  # the time since the first detection
        gap = (elapsed if second else torch.full_like(elapsed, float(self.dt))).to(z.dtype)
        gaps = torch.stack([gap, torch.full_like(gap, float(self.dt))], -1)
        gaps = gaps.view(B, *([1] * (z.dim() - 2)), 2).expand(*z.shape[:-1], 2)
        r2_track, P, _ = self._start(carry, z, second)  # the covariance with the prior (start_estimate: the estimate)
        adapt = {} if self.adapt is None else {keys.Q_SCALE: carry.get(keys.Q_SCALE)}
        out = super().start_carry(carry, z, x, second) | adapt | {
            keys.EXPERT_POST: per_expert(x, M).clone(),
            keys.EXPERT_RATE: self.rate_nominal.to(z.dtype).expand(B, M).clone(),
            keys.EXPERT_AUG_COV: P,
            keys.Z_HISTORY: torch.stack([z, prev, nan], -2),
            keys.INTERVAL_HISTORY: gaps.clone(),
            keys.NOISE_VAR: r2_track,
            keys.NOISE_SUM: carry.get(keys.NOISE_SUM),
            keys.NOISE_COUNT: carry.get(keys.NOISE_COUNT),
        }
        if self.robust is not None and z.dim() == 2:
            out = out | {keys.ROBUST_SPARE: torch.zeros(self._spare_shape(B), dtype=z.dtype, device=z.device)}
        if self.reacquire is None or z.dim() != 2:
            return out
        return out | dict(zip(REACQUIRE_CARRY, reacq.started(z, reacq.per_track_cov(out[keys.NOISE_VAR], B, z))))

    def _spare_shape(self, batch: int) -> tuple[int, ...]:
        """The robust update's carried ``spare`` (a far plot at the scan before): ``[B]``, or ``[B, G]`` per group."""
        return (batch,) if self.z_groups is None else (batch, len(self.z_groups))

    def start_cov(self, B: int, r2: torch.Tensor, second: bool, elapsed=None, r2_first=None) -> torch.Tensor:
        """Covariance of a starting track ``[B, M, 10, 10]``: after one scan position ``r^2``,
        velocity ``300^2``; after two (differenced velocity over ``elapsed``, the time between the
        detections ``[B]``; the nominal ``dt`` where None) velocity ``2 r^2 / elapsed^2`` with the
        position-velocity covariance ``r^2 / elapsed``; acceleration the CA draw's (``start_acc_std^2`` on every
        axis where set, for every expert or each its own), turn rate ``rate_std0``. ``r2`` ``[B, M]``, or each
        detection's covariance ``[B, M, 3, 3]`` (``r="detection"``): the position block ``R_1``, after two scans
        the velocity block ``(R_0 + R_1) / elapsed^2`` and the position-velocity block ``R_1 / elapsed``, ``R_0`` the
        first detection's (``r2_first``)."""
        if r2.dim() == 2:  # one variance per track and expert: r^2 I
            r2 = r2[..., None, None] * torch.eye(3, dtype=r2.dtype, device=r2.device)
        P = r2.new_zeros(B, self.n_experts, N_AUG, N_AUG)
        e = self.dt if elapsed is None else elapsed.to(r2.dtype).view(B, 1)
        first = r2 if r2_first is None else r2_first.to(r2.dtype)
        acc = self.start_acc_var.to(P.dtype)  # [M, 3]
        for a in range(3):
            for b in range(3):
                P[..., POS[a], POS[b]] = r2[..., a, b]
                if second:
                    P[..., VEL[a], VEL[b]] = (first[..., a, b] + r2[..., a, b]) / e**2
                    P[..., POS[a], VEL[b]] = P[..., VEL[b], POS[a]] = r2[..., a, b] / e
            if not second:
                P[..., VEL[a], VEL[a]] = 300.0**2
            P[..., ACC[a], ACC[a]] = acc[:, a]
        P[..., RATE, RATE] = torch.where(self.own_rate, self.rate_var0, 0.0).to(P.dtype)
        return P

    def _start(self, carry, z: torch.Tensor, second: bool, x: torch.Tensor | None = None):
        """``(r2_track, P, x)`` of a track's first or second detection ``z``: the noise the gain carries from it, the
        start covariance ``start_cov`` ``[B, M, 10, 10]`` and the start estimate ``x`` (``[B, 9]`` or ``[B, M, 9]``;
        None: not asked), each, with ``start_vz_std``, updated by the prior ``vz ~ N(0, start_vz_std^2)``
        (``immnet.imm.kalman.vertical_speed_prior``). Every expert's start covariance has the same velocity
        column, so every expert's estimate is the same: a ``[B, 9]`` ``x`` stays one."""
        M, told = self.n_experts, self.per_detection
        if told:
            r2_track = self._told_cov(carry, z)
        else:
            r2_track = self.noise_var(carry.get(keys.NOISE_SUM), carry.get(keys.NOISE_COUNT), carry)
        r2 = per_expert(r2_track, M, event_dims=2 if told else 0)
        first = per_expert(carry.get(keys.NOISE_VAR), M, event_dims=2) if told and second else None
        elapsed = carry.get(keys.START_TIME) if second else None  # the time since the first detection
        P = self.start_cov(z.shape[0], r2, second, elapsed, first)
        if self.start_vz_std is None:
            return r2_track, P, x
        xa = P.new_zeros(P.shape[:-1])  # the augmented state [x, w]; w's row of P is its own, untouched
        if x is not None:
            xa[..., :9] = per_expert(x, M)
        xa, P = vertical_speed_prior(xa, P, self.start_vz_std)
        return r2_track, P, None if x is None else (xa[..., :9] if x.dim() == 3 else xa[:, 0, :9])

    def start_estimate(self, carry, z: torch.Tensor, x: torch.Tensor, second: bool) -> torch.Tensor:
        """The start estimate fused with the prior on the vertical speed (``start_vz_std``; ``Stage.start_estimate``)."""
        return x if self.start_vz_std is None else self._start(carry, z, second, x)[2]

    # --- one scan ----------------------------------------------------------------------------
    def _r2(self, td) -> torch.Tensor:
        """This scan's ``r^2`` estimate as ``[B, M, 1, 1]``."""
        return noise_matrix(self.noise(td), self.n_experts, self.per_detection)

    def base_noise(self, td, like: torch.Tensor):
        """This scan's base process noise ``(Q_parts, scale, Q)``: its components (``q_parts``), their multipliers
        ``scale [B, M, 5]`` (the track's ``lambda``, ``AdaptiveNoise``, on the white-acceleration ones, 1 on the rest;
        None without adaptation) and ``Q [B, M, 10, 10]``, the components' sum with their multipliers."""
        Q_parts = self.q_parts(td, like)
        if self.adapt is None:
            return Q_parts, None, Q_parts.sum(-3)
        lam = per_expert(AdaptiveNoise.scale(td.get(keys.Q_SCALE)).to(like.dtype), self.n_experts, event_dims=0)
        scale = torch.where(self.white_mask, lam.unsqueeze(-1), torch.ones_like(lam).unsqueeze(-1))
        return Q_parts, scale, _noise(scale, Q_parts)

    def _adapt(self, td, maha: torch.Tensor, has_z: torch.Tensor) -> None:
        """The track's next ``log lambda`` from this scan's NIS ``maha [B, M]``: the smallest of the experts'
        (experts alone: each expert's own). An estimator, not a learned part: no gradient flows through it."""
        log_scale, maha = td.get(keys.Q_SCALE).detach(), maha.detach()
        if log_scale.dim() == 1:
            nis, ok = maha.min(-1).values, has_z[:, 0, 0]
        else:
            nis, ok = maha, has_z[..., 0]
        td.set(keys.Q_SCALE, self.adapt.update(log_scale, torch.where(ok, nis, 0.0), ok))

    def _loglik(self, nu, S, maha, logdet, has_z) -> torch.Tensor:
        """The innovation log-likelihood ``log N(nu; 0, S)`` per expert (``[B, M]``; modes per group each group's
        marginal, ``[B, G, M]``) of the squared Mahalanobis distance ``maha [B, M]``, 0 where the measurement is
        missing."""
        if self.z_groups is not None:  # each group's own likelihood, the marginal of its coordinates: [B, G, M]
            return torch.where(has_z, group_loglik(nu, S, self.z_groups), 0.0).transpose(1, 2)
        return torch.where(has_z[..., 0], gaussian_loglik(maha, logdet, 3), 0.0)

    def shifted_loglik(self, td, shift: torch.Tensor) -> torch.Tensor:
        """``("expert", "loglik")`` of a scan's output ``td`` had each expert predicted the measurement ``shift
        [B, 3]`` further (``log N(nu - shift; 0, S)``, the same ``S``: the prior covariance the scan kept and its
        ``r^2``). What a bank of networks weighs a network with an output correction by: its prediction moved by the
        correction it reported at the scan before (``IMMNet.predictive_loglik(reported=True)``)."""
        P = td.get(keys.EXPERT_AUG_PRIOR_COV)
        r2 = noise_matrix(td.get(keys.NOISE_VAR), self.n_experts, self.per_detection)
        S = innovation_cov(P, r2.to(P.dtype))
        nu = innovation(td.get(keys.MEASUREMENT), td.get(keys.EXPERT_PRIOR)) - shift.to(P.dtype).unsqueeze(1)
        has_z = measured(per_expert(td.get(keys.MEASUREMENT), self.n_experts))
        if self.z_groups is not None:  # each group's marginal (_loglik): no inverse of the whole S
            return self._loglik(nu, S, None, None, has_z)
        S_inv, logdet = inv3(S)
        return self._loglik(nu, S, quadratic(S_inv, nu), logdet, has_z)

    def _finish(self, td, r2, P, delta=None, nu=None):
        """Gain ``K = P H^T S^-1`` (+ the correction ``delta``, 9 x 3) of the prior covariance ``P``,
        zero where the measurement is missing; the innovation log-likelihood ``log N(nu; 0, S)``
        (``nu`` the innovation, if the caller has it)."""
        S = innovation_cov(P, r2)
        S_inv, logdet = inv3(S)
        has_z = measured(per_expert(td.get(keys.MEASUREMENT), self.n_experts))  # [B, M, 1]
        if nu is None:
            nu = innovation(td.get(keys.MEASUREMENT), td.get(keys.EXPERT_PRIOR))
        maha = quadratic(S_inv, nu)
        robust = self.robust
        after = None
        # the robust update's far plot at the scan before ([B, 1], per group [B, 1, G]); none experts alone, where
        # it is not carried
        carried = None if robust is None else td.get(keys.ROBUST_SPARE, None)
        spare = None if carried is None else carried[:, None] > 0
        if robust is not None and self.z_groups is not None:
            K, gain, loglik, after = self._robust_groups(td, P, S, nu, has_z, delta, spare)
        else:
            K = small_matmul(P[..., :, POS_VIEW], S_inv)  # [B, M, 10, 3]
            if robust is None:
                loglik = self._loglik(nu, S, maha, logdet, has_z)
            else:  # Huber's weight on an isolated far plot's Mahalanobis distance (immnet.imm.kalman)
                if spare is not None:
                    after = far(maha, robust, ~has_z[..., 0], spare)
                weight, rho = huber(maha, robust, spare)
                weight = torch.where(has_z[..., 0], weight, torch.ones_like(weight))
                K = K * weight[..., None, None]
                if delta is not None:  # the learned correction pulls towards a far plot no more than the Kalman gain
                    delta = delta * weight[..., None, None]
                loglik = torch.where(has_z[..., 0], gaussian_loglik(rho, logdet, 3), 0.0)
                td.set(keys.EXPERT_ROBUST_WEIGHT, weight)
            gain = K[..., :9, :] if delta is None else K[..., :9, :] + delta
        if self.reacquire is not None and td.get(keys.MEASUREMENT).dim() == 2:
            rejected = self._watch(td, r2, maha, nu, S)  # a far detection gated out: the experts take it as missed
            has_z = has_z & ~rejected[:, None, None]
            loglik = torch.where(rejected[:, None], 0.0, loglik)
            if robust is not None:
                td.set(keys.EXPERT_ROBUST_WEIGHT, torch.where(rejected[:, None], 1.0, td.get(keys.EXPERT_ROBUST_WEIGHT)))
            if after is not None:  # a plot gated out is not taken; a restarted track has no far plot before it
                after = torch.where(rejected[:, None], spare, after) & ~td.get(keys.REACQUIRE)[:, None]
        if after is not None:
            td.set(keys.ROBUST_SPARE, after[:, 0].to(P.dtype))
        td.set(keys.EXPERT_GAIN, torch.where(has_z.unsqueeze(-1), gain, 0.0))
        td.set(keys.EXPERT_RATE_GAIN, torch.where(has_z, K[..., RATE, :], 0.0))
        td.set(keys.EXPERT_AUG_PRIOR_COV, P)
        td.set(keys.EXPERT_LOGLIK, loglik)
        td.set(keys.EXPERT_NIS, torch.where(has_z[..., 0], maha, 0.0).detach())
        if self.adapt is not None:
            self._adapt(td, maha, has_z)
        return td

    def _robust_groups(self, td, P, S, nu, has_z, delta, spare):
        """Huber's update with modes per group (``_finish``'s ``(K, gain, loglik, spare after)``): each group's
        weight ``w_g = min(1, k / d_g)`` of its own marginal distance (``group_maha``; an isolated far plot's: the
        group's ``spare`` ``[B, 1, G]``, beyond ``k`` of every expert in that group; None: no far plot before, experts
        alone), the gain of ``S' = S + D S D``,
        ``D = diag(sqrt(1 / w - 1))`` per coordinate (``R' = R + D S D``: ``w_g`` times the Kalman gain where the groups'
        innovations are uncorrelated, as the per-axis IMM's per axis; ``FilterUpdate`` forms ``R'`` from the
        per-coordinate weights ``("expert", "robust_weight") [B, M, 3]``), the learned correction's columns weighted as
        their group's, each group's likelihood Huber's."""
        k = self.robust
        gm, logdet = group_maha(nu, S, self.z_groups)  # [B, M, G]
        # kalman.far over the experts, each group on its own: experts last, [B, G, M]
        after = None if spare is None else far(gm.transpose(1, 2), k, ~has_z[..., 0][:, None],
                                               spare.transpose(1, 2)).transpose(1, 2)
        w, rho = huber(gm, k, spare)
        w = torch.where(has_z, w, torch.ones_like(w))
        wc = w[..., self.coordinate_group]  # [B, M, 3]
        D = _inflation(wc)
        S2_inv, _ = inv3(S + D[..., :, None] * S * D[..., None, :])
        K = small_matmul(P[..., :, POS_VIEW], S2_inv)
        gain = K[..., :9, :] if delta is None else K[..., :9, :] + delta * wc[..., None, :]
        td.set(keys.EXPERT_ROBUST_WEIGHT, wc)
        loglik = torch.where(has_z, marginal_loglik(rho, logdet, self.z_groups), 0.0).transpose(1, 2)
        return K, gain, loglik, after

    def _watch(self, td, r2: torch.Tensor, maha: torch.Tensor, nu: torch.Tensor, S: torch.Tensor) -> torch.Tensor:
        """Re-acquisition's scan (``immnet.imm.reacquire.advance``) from the experts' innovations ``nu``, their
        covariances ``S`` and squared Mahalanobis distances ``maha``: the carried watch after this scan's detection and
        ``("expert", "reacquire") [B]``, the tracks that restart here (``IMMNet.scan`` restarts them); returns the
        tracks whose detection the experts do not take (gated out) ``[B]``."""
        z = td.get(keys.MEASUREMENT)
        B = z.shape[0]
        R = reacq.per_track_cov(r2[:, 0], B, z)
        dt, per_track = scan_interval(td, self.dt)
        state = reacq.Watch(*(td.get(k) for k in REACQUIRE_CARRY))
        interval = dt[:, 0] if per_track else dt
        reach = reacq.reachable(self.reacquire, nu.detach(), S.detach(), interval)
        state, restart, rejected = reacq.advance(self.reacquire, state, z, R, interval, maha.detach(), reach=reach)
        for key, value in zip(REACQUIRE_CARRY, state):
            td.set(key, value)
        td.set(keys.REACQUIRE, restart)
        return rejected


REACQUIRE_CARRY = (keys.REACQUIRE_COUNT, keys.REACQUIRE_PLOT, keys.REACQUIRE_COV, keys.REACQUIRE_ELAPSED)
"""What a filter gain with re-acquisition carries (``immnet.imm.reacquire.Watch``'s fields, in order)."""

_FILTER_IN = [keys.MEASUREMENT, keys.EXPERT_PRIOR, keys.EXPERT_AUG_PRIOR_COV, keys.NOISE_SUM, keys.NOISE_COUNT,
              keys.Z_HISTORY, keys.INTERVAL_HISTORY]
_FILTER_OUT = [
    keys.EXPERT_GAIN, keys.EXPERT_RATE_GAIN, keys.EXPERT_AUG_PRIOR_COV, keys.EXPERT_LOGLIK, keys.EXPERT_NIS,
    keys.NOISE_VAR, keys.NOISE_SUM, keys.NOISE_COUNT, keys.Z_HISTORY, keys.INTERVAL_HISTORY,
]


class FilterGain(_FilterExperts, Gain):
    """Filter experts with their base process noise and nothing learned: each expert is the
    extended Kalman filter of its own model (the ablation of the KalmanNet part; only the
    classifier trains)."""

    in_keys = _FILTER_IN
    out_keys = _FILTER_OUT

    def __init__(self, model_set: ModelSet, dt: float = 1.0, **options):
        """``options``: the filter experts' (``_FilterExperts._init_filter``: noise, interaction, measurement model,
        start, robust update, re-acquisition, modes per group)."""
        super().__init__(model_set)
        self._init_filter(model_set, dt, **options)

    def forward(self, td):
        r2 = self._r2(td)
        P = td.get(keys.EXPERT_AUG_PRIOR_COV)
        return self._finish(td, r2, P + self.base_noise(td, P)[2])


class KalmanNetFilterGain(_FilterExperts, KalmanNetGain):
    """KalmanNet architecture 2 that sets each filter expert's process noise and corrects its gain.

    ``u_max`` bounds the learned log-multiplier of each of the five process-noise components' variance (``u = u_max
    tanh(u_slope raw / u_max)``: a maneuver onset needs a turn-rate variance ~1e8 times the steady one, which the
    slope lets the network reach without large weights); ``gain_scale`` bounds the learned correction of the gain
    rows (position, velocity, acceleration). The filter experts' options (``noise_std``, ``r``, ``adapt``, ...) as
    ``FilterGain``'s (with ``model_noise`` the network scales the motion models' own ``Q``, the first component, and
    the others are zero). Beside F1..F4,
    GRU_S reads the innovation whitened by the base noise's ``S`` (times the adaptive scale, where on)
    (``nu / sqrt(diag S)``, a maneuver detector's statistic).
    """

    # written out, not KalmanNetGain.in_keys + [...]: tensordict turns a module's key lists into
    # properties once one is built, so a class body must not read another class's
    in_keys = [
        keys.PREV_MEASUREMENT, keys.FUSED, keys.PREV_FUSED, keys.PREV_EXPERT_PRIOR, keys.EXPERT_HIDDEN,
        keys.PREV_INTERVAL,
    ] + _FILTER_IN
    out_keys = [keys.EXPERT_HIDDEN, keys.PREV_INTERVAL] + _FILTER_OUT

    def __init__(
        self,
        model_set: ModelSet,
        dt: float = 1.0,
        in_mult: int = 5,
        out_mult: int = 4,
        u_max: float = 20.0,
        u_slope: float = 4.0,
        gain_scale: tuple[float, float, float] = (0.3, 0.3, 0.1),
        init_out_scale: float = 0.01,
        interval_input: bool = False,
        state_correction: tuple[float, float, float] | None = None,
        **options,
    ):
        """``options``: the filter experts' (``_FilterExperts._init_filter``) but the oracles ``turn_rate`` and
        ``restart`` (Huber's weight ``w`` bounds the whole gain, the learned correction ``delta`` with the Kalman part:
        ``w (K + delta)``)."""
        oracles = sorted(name for name in ("turn_rate", "restart") if options.get(name) is not None)
        if oracles:
            raise ValueError(f"KalmanNetFilterGain takes no {', '.join(oracles)} (FilterGain's oracles)")
        if not (u_max > 0 and u_slope > 0):
            raise ValueError(f"u_max and u_slope must be > 0, got {u_max}, {u_slope}")
        if state_correction is not None and (len(state_correction) != 3 or not all(
                math.isfinite(float(v)) and float(v) > 0 for v in state_correction)):
            raise ValueError("state_correction needs three bounds > 0 (position m, velocity m/s, acceleration "
                             f"m/s^2) or None, got {state_correction!r}")
        super().__init__(model_set, dt, in_mult, out_mult, gain_scale=gain_scale, init_out_scale=init_out_scale,
                         interval_input=interval_input)
        M, n = self.n_experts, 3
        # F1, F2 (with the interval, where an input) and the whitened innovation into GRU_S; FC2 gives the 27
        # gain corrections and 5 noise scales (and, with state_correction, 9 state corrections)
        self.fc7 = StackedLinear(M, 3 * n + int(self.interval_input), 2 * n * in_mult)
        d2 = self.d_s + self.d_sigma
        self.n_correction = 0 if state_correction is None else 9
        self.fc2b = StackedLinear(M, d2 * out_mult, 9 * n + N_NOISE + self.n_correction)
        self.state_correction = None if state_correction is None else tuple(float(v) for v in state_correction)
        if self.state_correction is not None:
            self.register_buffer("correction_scale", state_scale(*self.state_correction), persistent=False)
            self.out_keys = [*self.out_keys, keys.EXPERT_CORRECTION]
        with torch.no_grad():
            self.fc2b.weight.mul_(init_out_scale)
            self.fc2b.bias.zero_()
        self._init_filter(model_set, dt, **options)
        self.u_max, self.u_slope = float(u_max), float(u_slope)

    def base_gain(self, model_set: ModelSet, sigma_q: float, r: float, dt: float) -> None:
        """None: the base gain is each filter expert's own Kalman gain (no steady-state ``K_ss``)."""

    def knock_out_correction(self) -> None:
        """Set the state correction's rows of FC2 to zero (the rest of the network as trained)."""
        if self.state_correction is None:
            raise ValueError("this KalmanNetFilterGain has no state correction (state_correction=None)")
        with torch.no_grad():
            self.fc2b.weight[:, -self.n_correction:].zero_()
            self.fc2b.bias[:, -self.n_correction:].zero_()

    def forward(self, td):
        r2 = self._r2(td)
        base = td.get(keys.EXPERT_AUG_PRIOR_COV)
        Q_parts, scale, Q0 = self.base_noise(td, base)  # the whitening below uses the scaled noise too
        S0 = innovation_cov(base + Q0, r2)
        nu = innovation(td.get(keys.MEASUREMENT), td.get(keys.EXPERT_PRIOR))
        white = slog(nu / torch.diagonal(S0, dim1=-2, dim2=-1).sqrt(), 1.0)
        f1, f2, f3, f4, white = (f.transpose(0, 1) for f in (*self.features(td), white))
        out = self.recur(td, f1, torch.cat([f2, white], -1), f3, f4)
        u = out[..., 9 * 3 : 9 * 3 + N_NOISE].transpose(0, 1)
        u = self.u_max * torch.tanh(u * (self.u_slope / self.u_max))  # [B, M, 5]
        if self.state_correction is not None:  # a bounded additive correction of each expert's posterior
            c = torch.tanh(out[..., 9 * 3 + N_NOISE :].transpose(0, 1))
            td.set(keys.EXPERT_CORRECTION, self.correction_scale.to(c.dtype) * c)
        P = base + _noise(torch.exp(u) if scale is None else torch.exp(u) * scale, Q_parts)
        delta = self.K_scale * torch.tanh(out[..., : 9 * 3].transpose(0, 1).unflatten(-1, (9, 3)))
        return self._finish(td, r2, P, delta, nu)


