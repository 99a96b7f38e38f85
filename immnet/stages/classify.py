"""Stage 4, classify: mode probabilities ``mu_t`` over the experts.

``TransformerClassifier`` (the paper's Transformer, docs/spec.md section 4): an encoder over the last
``W`` scans of two streams, measurements ``z_tau`` and fused estimates ``x_{tau-1|tau-1}``, in a
frame that is translation-invariant and scaled: positions relative to the latest fused estimate
``x_{t-1|t-1}``, the horizontal plane rotated to its heading, residuals against the
constant-velocity guess ``p_ref + v_ref (tau - t + 1) dt``, each through ``slog``. As in the paper,
the two streams are concatenated along the feature dimension (one token per scan), so
self-attention over time relates scans within and across the streams; one token set of ``W``
rather than two of ``W`` halves the cost, which dominates a training step. Each expert's current innovation (rotated, scaled)
joins the pooled encoding in the head: it says which expert's prediction fits ``z_t``.

Ablations, same keys: ``UniformMix`` (``mu = 1/M``) and ``BayesianModeUpdate`` (the IMM's
``mu_t ∝ N(nu^(i); 0, S^(i)) (Pi^T mu_{t-1})^(i)`` with each expert's steady-state ``S``).
"""

from __future__ import annotations

import torch
from torch import nn

from immnet import keys
from immnet.imm.interaction import transition_matrix
from immnet.imm.kalman import gaussian_loglik, inv3
from immnet.imm.option import flag
from immnet.motion import ACC_VIEW, CT_NEG, CT_POS, MODE_NAMES, N_MODES, POS_VIEW, VEL_VIEW, ModelSet, Modes
from immnet.stages.base import Stage, measured, per_expert
from immnet.stages.correct import noise_covariance, std_of
from immnet.stages.features import slog
from immnet.stages.update import innovation

_MODE_KEYS_IN = [keys.MEASUREMENT, keys.FUSED, keys.EXPERT_PRIOR]
_MODE_KEYS_OUT = [keys.MODE_LOGITS, keys.EXPERT_PROBS]


def heading_frame(v: torch.Tensor):
    """cos and sin of the horizontal heading of velocities ``v [B, 3]`` (heading 0 when at rest, with a zero gradient
    there: ``std_of``)."""
    speed = std_of(v[:, 0] ** 2 + v[:, 1] ** 2)
    ok = speed > 1e-3
    c = torch.where(ok, v[:, 0] / speed.clamp_min(1e-3), 1.0)
    s = torch.where(ok, v[:, 1] / speed.clamp_min(1e-3), 0.0)
    return c, s


def rotate(d: torch.Tensor, c: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Express ``d [B, ..., 3]`` in the heading frame: (along-track, left, up)."""
    shape = (-1,) + (1,) * (d.dim() - 2)
    c, s = c.view(shape), s.view(shape)
    along = c * d[..., 0] + s * d[..., 1]
    left = -s * d[..., 0] + c * d[..., 1]
    return torch.stack([along, left, d[..., 2]], -1)


class _Block(nn.Module):
    """Pre-norm Transformer encoder block (multi-head self-attention + MLP)."""

    def __init__(self, d: int, heads: int, ff: int):
        super().__init__()
        self.heads = heads
        self.norm1, self.norm2 = nn.LayerNorm(d), nn.LayerNorm(d)
        self.qkv = nn.Linear(d, 3 * d)
        self.proj = nn.Linear(d, d)
        self.ff = nn.Sequential(nn.Linear(d, ff), nn.GELU(), nn.Linear(ff, d))

    def forward(self, x, mask):
        B, L, D = x.shape
        q, k, v = self.qkv(self.norm1(x)).view(B, L, 3, self.heads, D // self.heads).permute(2, 0, 3, 1, 4)
        # softmax(q k^T / sqrt(d) masked) v in one fused kernel: for a window of 20 tokens on CPU, faster than
        # the explicit product, softmax and product (benchmarks/bench_immnet.py's stage table)
        a = nn.functional.scaled_dot_product_attention(q, k, v, attn_mask=mask)
        x = x + self.proj(a.transpose(1, 2).reshape(B, L, D))
        return x + self.ff(self.norm2(x))


class ModeUpdate(Stage):
    """The classifier's role: each expert's probability at this scan (``("expert", "probs")``), which the fusion
    weighs the experts by. ``markov_prior(td, prev)``: the log prior ``log (Pi^T mu_{t-1})`` a Bayesian mode update
    predicts the modes with, None for one that has none (``IMMNet.innovation_loglik`` weighs a track by it)."""

    markov_prior = None
    shared = ("modes",)

    def __init__(self, model_set: ModelSet, modes: str = "joint"):
        """``modes``: one set of mode probabilities or one per group (``IMMNet``'s, set there once)."""
        super().__init__(model_set)
        self.modes = Modes.parse(modes)
        self.groups = self.modes.n_groups

    def carry_spec(self, batch: int, experts_alone: bool = False, dtype=torch.float32, device=None) -> dict:
        """The mode probabilities before a track starts: uniform, ``mu = 1/M`` ``[B, M]`` (per group, ``[B, G, M]``)."""
        M = self.n_experts
        shape = (batch, M) if self.groups is None else (batch, self.groups, M)
        return {keys.EXPERT_PROBS: torch.full(shape, 1.0 / M, dtype=dtype, device=device)}

    @staticmethod
    def set_logits(td, logits: torch.Tensor) -> None:
        """Write the mode logits and the experts' probabilities, their softmax."""
        td.set(keys.MODE_LOGITS, logits)
        td.set(keys.EXPERT_PROBS, torch.softmax(logits, -1))


class TransformerClassifier(ModeUpdate):
    in_keys = _MODE_KEYS_IN + [keys.HISTORY, keys.HISTORY_LEN, keys.HISTORY_INTERVAL]
    out_keys = _MODE_KEYS_OUT + [keys.HISTORY, keys.HISTORY_LEN, keys.HISTORY_INTERVAL]

    def __init__(
        self,
        model_set: ModelSet,
        dt: float = 1.0,
        window: int = 20,
        d_model: int = 32,
        heads: int = 4,
        layers: int = 2,
        ff: int = 64,
        interval_input: bool = False,
        modes: str = "joint",
        whiten: bool = False,
    ):
        """``interval_input``: each token also reads its scan's interval, ``log(interval / dt)`` (a network
        trained over a range of intervals, docs/stages.md "Any scan interval"). ``modes``: modes per group
        (``IMMNet``'s, set there once): the head gives logits per group and mode, ``[B, G, M]``. ``whiten``: the
        classifier is told the plot's noise (``("memory", "r2")``, each detection's covariance where the filter
        experts are told it): every position feature in units of the noise's standard deviation along each axis of
        the heading frame (``noise_scale``) in place of fixed metres, and the head also reads ``log(scale / 5 m)``."""
        super().__init__(model_set, modes)
        self.window, self.dt, self.interval_input = window, dt, flag(interval_input, "interval_input")
        self.whiten = flag(whiten, "whiten")
        if self.whiten:
            self.in_keys = [*self.in_keys, keys.NOISE_VAR]
        self.embed = nn.Linear(6 + 12 + int(self.interval_input), d_model)
        self.pos = nn.Parameter(torch.randn(window, d_model) * 0.02)
        self.blocks = nn.ModuleList(_Block(d_model, heads, ff) for _ in range(layers))
        self.norm = nn.LayerNorm(d_model)
        M = self.n_experts
        self.head = nn.Sequential(nn.Linear(d_model + 3 * M + 3 * self.whiten, 64), nn.GELU(),
                                  nn.Linear(64, M * (self.groups or 1)))

    def interval_columns(self) -> dict[str, int]:
        """The weights that read the interval input and its column (each token's last feature)."""
        return {"embed.weight": 6 + 12} if self.interval_input else {}

    def group_rows(self) -> dict[str, int]:
        """The weights whose rows are one block per group of modes (the head's last layer: ``G M`` logits) and the
        number of groups; none with one joint set of modes."""
        return {} if self.groups is None else {"head.2.weight": self.groups, "head.2.bias": self.groups}

    def carry_spec(self, batch: int, experts_alone: bool = False, dtype=torch.float32, device=None) -> dict:
        """The mode probabilities (uniform) and an empty window."""
        return super().carry_spec(batch, experts_alone, dtype, device) | {
            keys.HISTORY: torch.zeros(batch, self.window, 12, dtype=dtype, device=device),
            keys.HISTORY_LEN: torch.zeros(batch, dtype=torch.long, device=device),
            keys.HISTORY_INTERVAL: torch.full((batch, self.window), float(self.dt), dtype=dtype, device=device),
        }

    def start_carry(self, carry, z: torch.Tensor, x: torch.Tensor, second: bool) -> dict:
        """At a track's second detection the window holds the scan the first stored, ``(z_1, x_0)``."""
        if not second:
            return {}
        return {keys.HISTORY_LEN: torch.ones_like(carry.get(keys.HISTORY_LEN)), keys.HISTORY: carry.get(keys.HISTORY),
                keys.HISTORY_INTERVAL: carry.get(keys.HISTORY_INTERVAL)}

    def tokens(self, hist, fused, gaps=None, noise=None):
        """Frame the window: ``hist [B, W, 12]`` of (z_tau, x_{tau-1}) against ``fused = x_{t-1|t-1}``;
        ``gaps [B, W]`` the interval before each entry's scan (None: the nominal ``dt`` at every scan); ``noise``
        (``whiten``): the plot's covariance ``[B, 3, 3]``, the positions then in units of ``noise_scale``. Returns the
        two streams' tokens and ``(c, s, scale)``, ``scale [B, 3]`` (None without ``noise``)."""
        W = self.window
        p_ref, v_ref = fused[:, POS_VIEW], fused[:, VEL_VIEW]
        c, s = heading_frame(v_ref)
        scale = None if noise is None else noise_scale(noise.to(fused.dtype), c, s)

        def position(d, metres):  # a position difference, rotated: slog of metres, or of noise stds (whiten)
            d = rotate(d, c, s)
            return slog(d, metres) if scale is None else slog(d / scale[:, None], 1.0)

        # scan tau = t - W + 1 + k holds z_tau; its CV guess is p_ref + v_ref (time(tau) - time(t - 1))
        if gaps is None:  # (tau - t + 1) dt
            lag = torch.arange(W, device=hist.device, dtype=hist.dtype) - (W - 2)
            guess_z = p_ref[:, None] + v_ref[:, None] * (lag * self.dt)[None, :, None]
        else:  # time(tau_k) - time(t - 1) = gap_t - (the gaps after entry k)
            after = gaps.flip(-1).cumsum(-1).flip(-1) - gaps
            rel = gaps[:, -1:] - after
            guess_z = p_ref[:, None] + v_ref[:, None] * rel[..., None]
        z = hist[..., :3]
        tz = torch.cat([position(z - p_ref[:, None], 100.0), position(z - guess_z, 10.0)], -1)
        x = hist[..., 3:]
        px, vx, ax = x[..., POS_VIEW], x[..., VEL_VIEW], x[..., ACC_VIEW]
        guess_x = guess_z - v_ref[:, None] * (self.dt if gaps is None else gaps[..., None])
        tx = torch.cat(
            [
                position(px - p_ref[:, None], 100.0),
                slog(rotate(vx - v_ref[:, None], c, s), 10.0),
                slog(rotate(ax, c, s), 1.0),
                position(px - guess_x, 10.0),
            ],
            -1,
        )
        return tz, tx, (c, s, scale)

    def forward(self, td):
        # the window is an input, not a path for gradients into the experts: detaching it keeps
        # the backward pass short (the experts learn from the state loss through the fusion)
        z = td.get(keys.MEASUREMENT)
        fused = td.get(keys.FUSED).detach()
        hist, n = td.get(keys.HISTORY).detach(), td.get(keys.HISTORY_LEN)
        interval = td.get(keys.INTERVAL, None)
        gaps = td.get(keys.HISTORY_INTERVAL)
        # the window's intervals move with it (unchanged at the nominal interval)
        gaps = gaps.clone() if interval is None else torch.cat([gaps[:, 1:], interval.to(gaps.dtype)[:, None]], 1)
        step = self.dt if interval is None else interval.to(fused.dtype)[:, None]
        # a missing measurement enters the window as the predicted position of the fused estimate
        z_fill = torch.where(measured(z), z, fused[:, POS_VIEW] + fused[:, VEL_VIEW] * step)
        hist = torch.cat([hist[:, 1:], torch.cat([z_fill, fused], -1)[:, None]], 1)
        n = (n + 1).clamp(max=self.window)
        noise = noise_covariance(td.get(keys.NOISE_VAR)) if self.whiten else None
        tz, tx, (c, s, scale) = self.tokens(hist, fused, None if interval is None else gaps, noise)
        feats = [tz, tx]
        if self.interval_input:
            feats.append(torch.log(gaps / self.dt).to(tz.dtype).unsqueeze(-1))
        h = self.embed(torch.cat(feats, -1)) + self.pos
        valid = torch.arange(self.window, device=n.device)[None] >= (self.window - n)[:, None]  # [B, W]
        mask = valid[:, None, None, :]
        for block in self.blocks:
            h = block(h, mask)
        h = self.norm(h)
        w = valid.to(h.dtype).unsqueeze(-1)
        pooled = (h * w).sum(1) / w.sum(1).clamp_min(1.0)
        nu = rotate(innovation(z, td.get(keys.EXPERT_PRIOR).detach()), c, s)
        if scale is None:
            logits = self.head(torch.cat([pooled, slog(nu, 10.0).flatten(1)], -1))
        else:  # each expert's innovation in noise stds, and the noise's scale
            logits = self.head(torch.cat([pooled, slog(nu / scale[:, None], 1.0).flatten(1),
                                          torch.log(scale / NOISE_UNIT)], -1))
        if self.groups is not None:
            logits = logits.unflatten(-1, (self.groups, self.n_experts))
        self.set_logits(td, logits)
        td.set(keys.HISTORY, hist)
        td.set(keys.HISTORY_LEN, n)
        td.set(keys.HISTORY_INTERVAL, gaps)
        return td


NOISE_UNIT = 5.0
"""Metres: the noise scale the whitened classifier's head reads as ``log(scale / NOISE_UNIT)``."""


def noise_scale(R: torch.Tensor, c: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """The standard deviations ``[B, 3]`` of noise ``R [B, 3, 3]`` (east, north, up) along the heading frame's axes
    (``rotate``'s along-track, left, up; ``c``, ``s`` the heading's cosine and sine): the square roots of the diagonal
    of ``Rot R Rot^T``."""
    along = c * c * R[:, 0, 0] + 2 * c * s * R[:, 0, 1] + s * s * R[:, 1, 1]
    left = s * s * R[:, 0, 0] - 2 * c * s * R[:, 0, 1] + c * c * R[:, 1, 1]
    return torch.stack([along, left, R[:, 2, 2]], -1).clamp_min(1e-6).sqrt()


def markov_prior(prev: torch.Tensor, log_pi: torch.Tensor, transition: torch.Tensor | None = None) -> torch.Tensor:
    """The IMM's predicted mode log-probabilities ``log (Pi^T mu_{t-1})`` ``[B, M]`` from ``mu_{t-1} [B, M]`` (modes
    per group: ``[B, G, M]`` from ``[B, G, M]``, each group's chain the same).

    The transition the step's IMM interaction mixed with, ``transition [B, M, M]`` (``("mode", "transition")``;
    per track where a range guard, ``immnet.imm.guard``, makes it state-dependent), is used instead of
    ``log_pi``, so that the mode update predicts with the transitions the experts were mixed with."""
    if transition is not None:
        transition = transition.to(prev.dtype) if prev.dim() == 2 else transition.to(prev.dtype).unsqueeze(1)
        return torch.log((prev.unsqueeze(-1) * transition).sum(-2).clamp_min(1e-30))
    return torch.logsumexp(torch.log(prev.clamp_min(1e-30)).unsqueeze(-1) + log_pi, dim=-2)


class _MarkovPrior:
    """What the Bayesian mode updates share: the Markov prior ``log (Pi^T mu_{t-1})``, from the
    transition matrix the step's IMM interaction writes (``("mode", "transition")``: the chain the experts
    were mixed with, guarded or not) where it writes one (``wire``), else from ``log_pi`` (its own
    ``p_stay``: a step without the IMM interaction). ``log_pi`` is derived from ``p_stay``, not a weight:
    a checkpoint's stored copy is not loaded."""

    reads_transition = False

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        state_dict.pop(prefix + "log_pi", None)  # derived from p_stay (checkpoints that stored it)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def wire(self, upstream: set) -> None:
        if keys.MODE_TRANSITION in upstream and not self.reads_transition:
            self.reads_transition = True
            self.in_keys = [*self.in_keys, keys.MODE_TRANSITION]

    def markov_prior(self, td, prev: torch.Tensor) -> torch.Tensor:
        transition = td.get(keys.MODE_TRANSITION) if self.reads_transition else None
        return markov_prior(prev, self.log_pi.to(prev.dtype), transition)


class UniformMix(ModeUpdate):
    """Ablation: a fixed uniform mix ``mu = 1/M``."""

    in_keys = [keys.FUSED]
    out_keys = _MODE_KEYS_OUT

    def __init__(self, model_set: ModelSet, dt: float = 1.0, modes: str = "joint"):
        super().__init__(model_set, modes)

    def forward(self, td):
        x = td.get(keys.FUSED)
        logits = x.new_zeros(x.shape[0], *(() if self.groups is None else (self.groups,)), self.n_experts)
        self.set_logits(td, logits)
        return td


class TrueModeUpdate(ModeUpdate):
    """An oracle in the classifier's slot: the mode probabilities are the truth's, one-hot on the expert of the
    data's mode at each scan (the step's input ``("truth", "mode")`` ``[B]``), also at a track's start. A bound, not a
    tracker: with it the IMM's interaction takes each expert's prior from the true mode's expert (a mix with one-hot
    weights), with the onset priors where the mode switched, and the fusion is the true mode's expert alone: the
    clairvoyant filters' configuration (``immnet.filters.clairvoyant``, docs/core.md).

    ``experts``: the expert of each data mode (CV, CA, CT+, CT-), four indices; None: each data mode's own expert
    (``ModelSet.modes``), a turn of one sign standing for both where the set has only that one (a turn filter told the
    truth's rate turns either way). A data mode without an expert is a ValueError naming it."""

    in_keys = [keys.TRUE_MODE]
    out_keys = _MODE_KEYS_OUT

    def __init__(self, model_set: ModelSet, dt: float = 1.0, experts: list[int] | None = None, modes: str = "joint"):
        super().__init__(model_set, modes)
        if self.modes is not Modes.JOINT:
            raise ValueError(f"the truth's modes are the whole target's: TrueModeUpdate takes modes='joint', got "
                             f"{self.modes.value!r}")
        M = self.n_experts
        if experts is None:
            own = model_set.modes.tolist()
            experts = []
            for mode, name in enumerate(MODE_NAMES):
                other = {CT_POS: CT_NEG, CT_NEG: CT_POS}.get(mode)
                found = [i for i, m in enumerate(own) if m == mode] or [i for i, m in enumerate(own) if m == other]
                if not found:
                    raise ValueError(f"TrueModeUpdate: the data mode {name!r} has no expert in the model set "
                                     f"{model_set.names}; give experts=[...] (one index per data mode)")
                experts.append(found[0])
        if len(experts) != N_MODES or not all(isinstance(i, int) and 0 <= i < M for i in experts):
            raise ValueError(f"experts needs one expert index in [0, {M}) per data mode {MODE_NAMES}, got {experts!r}")
        self.experts = list(experts)
        self.register_buffer("expert_of", torch.tensor(self.experts), persistent=False)
        self.register_buffer("onehot", torch.eye(M), persistent=False)  # each expert's row, in the network's dtype

    def _onehot(self, mode: torch.Tensor) -> torch.Tensor:
        """``[B, M]``: 1 on the expert of each track's data mode ``mode [B]``; a ValueError (eager) where a mode is
        not one of the four (``-1``: a scan without a label, as real flights have)."""
        mode = mode.long()
        if not torch.compiler.is_compiling() and bool(((mode < 0) | (mode >= N_MODES)).any()):
            raise ValueError(f"TrueModeUpdate needs the truth's mode at every scan, one of {MODE_NAMES} (0-3); this scan "
                             "has a track without one (-1: real flights, padding)")
        return self.onehot[self.expert_of[mode]]

    def start_carry(self, carry, z: torch.Tensor, x: torch.Tensor, second: bool) -> dict:
        """At a track's start its modes are the truth's there."""
        return {keys.EXPERT_PROBS: self._onehot(carry.get(keys.TRUE_MODE)).to(z.dtype)}

    def forward(self, td):
        probs = self._onehot(td.get(keys.TRUE_MODE))
        td.set(keys.MODE_LOGITS, torch.log(probs))
        td.set(keys.EXPERT_PROBS, probs)
        return td


class BayesianModeUpdate(_MarkovPrior, ModeUpdate):
    """Ablation: the IMM's Bayesian mode update with a Markov transition ``Pi`` (``p_stay`` on the diagonal).

    ``mu_t^(i) ∝ N(nu_t^(i); 0, S^(i)) sum_j Pi_ji mu_{t-1}^(j)``, in log space; ``S^(i)`` is the
    expert's steady-state innovation covariance for ``sigma_q`` and ``r``, or, with
    ``from_experts``, the filter experts' own likelihoods (``("expert", "loglik")``, each with its
    own ``S``: the IMM's mode update exactly). ``modes`` (``IMMNet``'s, set there once; with ``from_experts``):
    modes per group, each group's update from the experts' likelihoods of its coordinates, ``[B, G, M]``.
    """

    in_keys = [keys.MEASUREMENT, keys.EXPERT_PRIOR, keys.EXPERT_PROBS]
    out_keys = _MODE_KEYS_OUT

    shared = ("p_stay", "modes")

    def __init__(self, model_set: ModelSet, dt: float = 1.0, p_stay: float = 0.9, sigma_q: float = 1.0, r: float = 4.0,
                 from_experts: bool = False, modes: str = "joint"):
        super().__init__(model_set, modes)
        if self.modes is not Modes.JOINT and not from_experts:
            raise ValueError(f"modes per group (modes={self.modes.value!r}) need the filter experts' likelihoods per "
                             "group: from_experts=True")
        from immnet.stages.gain import steady_state

        M = self.n_experts
        if not 0.0 < p_stay <= 1.0:
            raise ValueError(f"p_stay must be in (0, 1], got {p_stay}")
        self.p_stay = float(p_stay)
        off = (1.0 - p_stay) / max(M - 1, 1)
        Pi = torch.full((M, M), off) + torch.eye(M) * (p_stay - off)
        self.register_buffer("log_pi", torch.log(Pi.clamp_min(1e-30)), persistent=False)
        self.from_experts = bool(from_experts)
        if self.from_experts:
            self.in_keys = [keys.EXPERT_LOGLIK, keys.EXPERT_PROBS]
        else:
            _, _, S = steady_state(model_set, sigma_q, r, dt)
            S_inv, logdet = inv3(S)
            self.register_buffer("S_inv", S_inv.float())
            self.register_buffer("log_norm", gaussian_loglik(torch.zeros_like(logdet), logdet, 3).float())  # at nu = 0

    def forward(self, td):
        if self.from_experts:
            loglik = td.get(keys.EXPERT_LOGLIK)
        else:
            nu = innovation(td.get(keys.MEASUREMENT), td.get(keys.EXPERT_PRIOR))
            has_z = measured(per_expert(td.get(keys.MEASUREMENT), self.n_experts))[..., 0]
            loglik = self.log_norm - 0.5 * torch.einsum("bmi,mij,bmj->bm", nu, self.S_inv, nu)
            loglik = torch.where(has_z, loglik, 0.0)
        prev = td.get(keys.EXPERT_PROBS)
        self.set_logits(td, self.markov_prior(td, prev) + loglik)
        return td


class BayesTransformerClassifier(_MarkovPrior, TransformerClassifier):
    """The IMM's Bayesian mode update, corrected by the Transformer: logits
    ``log (Pi^T mu_{t-1}) + log N(nu^(i); 0, S^(i)) + transformer(window)``.

    The first two terms are ``BayesianModeUpdate(from_experts=True)``: each filter expert's own
    innovation likelihood (``("expert", "loglik")``) and a Markov prior with ``p_stay`` on the
    diagonal. The Transformer (``TransformerClassifier``, same inputs and frame) adds a learned
    correction in log space; its head's last layer starts at zero, so an untrained classifier is the
    IMM's mode update exactly, and training moves it only where the data says the IMM is wrong.
    """

    # written out: tensordict turns a built module's key lists into properties (see filtering.py)
    in_keys = _MODE_KEYS_IN + [keys.HISTORY, keys.HISTORY_LEN, keys.HISTORY_INTERVAL, keys.EXPERT_LOGLIK,
                               keys.EXPERT_PROBS]
    out_keys = _MODE_KEYS_OUT + [keys.HISTORY, keys.HISTORY_LEN, keys.HISTORY_INTERVAL]

    shared = ("p_stay", "modes")

    def __init__(self, model_set: ModelSet, dt: float = 1.0, p_stay: float = 0.995, window: int = 20,
                 d_model: int = 32, heads: int = 4, layers: int = 2, ff: int = 64, interval_input: bool = False,
                 modes: str = "joint", whiten: bool = False):
        super().__init__(model_set, dt, window, d_model, heads, layers, ff, interval_input, modes, whiten)
        if not 0.0 < p_stay <= 1.0:
            raise ValueError(f"p_stay must be in (0, 1], got {p_stay}")
        self.p_stay = float(p_stay)
        self.register_buffer("log_pi", torch.log(transition_matrix(p_stay, self.n_experts).clamp_min(1e-300)), persistent=False)
        self.knock_out()

    def knock_out(self) -> None:
        """Set the Transformer's correction to zero (its head's last layer): the IMM's mode update exactly. An
        untrained classifier starts so; on a trained one it measures what the correction is worth
        (docs/notebook/real-flights.md, "What each learned part is worth")."""
        with torch.no_grad():
            self.head[-1].weight.zero_()
            self.head[-1].bias.zero_()

    def forward(self, td):
        prev = td.get(keys.EXPERT_PROBS)
        bayes = self.markov_prior(td, prev) + td.get(keys.EXPERT_LOGLIK)
        td = super().forward(td)
        self.set_logits(td, bayes + td.get(keys.MODE_LOGITS))
        return td
