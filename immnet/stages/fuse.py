"""Stage 5, fuse: ``x_t = sum_i mu_t^(i) x_{t|t}^(i)``, and the step's memory moves on one scan.

The fused estimate it replaces becomes ``x_{t-2|t-2}`` for the next step's F3, the experts' priors
become ``x_{t-1|t-2}^(i)`` for F4, and ``z_t`` (or, when missing, the fused position) becomes
``z_{t-1}`` for F1. Where the experts carry a covariance it also fuses the covariances (moment matching,
the IMM's combination),

    P_t = sum_i mu^(i) (P^(i) + (x^(i) - x_t)(x^(i) - x_t)^T),

``P^(i)`` the analytic gain's ``("expert", "cov")`` ``[B, M, 9, 9]``, or the 9x9 state block of a filter
expert's posterior covariance of ``[x, w]``, ``("expert", "aug_cov")`` ``[B, M, 10, 10]``. The paper's
KalmanNet experts (a gain only) carry none: then there is no fused covariance. With modes per group
(``mu [B, G, M]``, ``IMMNet(modes="axis" | "channel")``) each coordinate is fused with its group's probabilities and
each group's covariance block with them, the blocks across groups 0 (independent IMMs, one per group).

``consistency`` (a weight ``a`` in (0, 1]; off by default) scales the covariance the tracker *reports* by a running
mean of the normalized innovation squared: ``lambda_t = (1 - a) lambda_{t-1} + a min(sum_i mu^(i) NIS^(i) / 3, 10)``
at each scan with a detection (``NIS^(i) = nu^T S^-1 nu`` of expert ``i``, ``("expert", "nis")``, 3 in expectation
where its covariance is right; ``lambda`` starts at 1 with each track and is carried, ``("memory", "cov_scale")``).
It is covariance matching on the output alone: the state, the experts' covariances and everything the next scan
reads are unchanged; ``IMMNet.reported_cov`` multiplies ``P_t`` by ``lambda_t`` (docs/immnet.md, "Covariance
consistency"). A network whose learned noise makes its covariance too small on data unlike its training data
(real flights for a network trained mostly on 3D-LAST) then reports a wider one, where its innovations say so.

``per_expert=True`` is stage-1 training: each expert runs alone, its own posterior is its fused
estimate (``[B, M, 9]``, its covariance its own) and no mode probabilities are needed. ``cov`` (the key of
the experts' covariances; ``wire``d on where a stage before it writes one) fuses them too.
"""

from __future__ import annotations

import torch

from immnet import keys
from immnet.imm.interaction import moment_match
from immnet.motion import POS_VIEW, Modes
from immnet.stages.base import Stage, axis_probs, block_weights, coordinate_weights, measured, per_expert

COV_KEYS = (keys.EXPERT_COV, keys.EXPERT_AUG_COV)
"""The experts' covariances ``Fuse`` fuses, first found first: the analytic gain's, the filter experts'."""


class Fuse(Stage):
    in_keys = [keys.EXPERT_POST, keys.EXPERT_PROBS, keys.FUSED, keys.EXPERT_PRIOR, keys.MEASUREMENT]
    out_keys = [keys.FUSED, keys.PREV_FUSED, keys.PREV_EXPERT_PRIOR, keys.PREV_MEASUREMENT]

    shared = ("modes",)

    def __init__(self, model_set=None, per_expert: bool = False, cov=None, consistency: float | None = None,
                 modes: str = "joint"):
        """``cov``: the key of the experts' covariances to fuse (one of ``COV_KEYS``), or None (as ``wire`` finds).
        ``consistency``: the weight of each scan in the reported covariance's scale (module doc), or None (off);
        not with ``per_expert`` (stage 1 reports no covariance). ``modes``: ``IMMNet``'s (module doc)."""
        super().__init__(model_set)
        groups = Modes.parse(modes).groups  # the group of each coordinate as a buffer: no copy to the device each scan
        self.register_buffer("groups", None if groups is None else torch.tensor(groups), persistent=False)
        if consistency is not None:
            consistency = float(consistency)
            if not 0.0 < consistency <= 1.0:
                raise ValueError(f"consistency is a weight in (0, 1] (or None: off), got {consistency}")
            if per_expert:
                raise ValueError("consistency scales the fused covariance: not with per_expert (experts alone)")
        self.per_expert = per_expert
        self.consistency = consistency
        self.cov = None
        if per_expert:
            self.in_keys = [k for k in self.in_keys if k != keys.EXPERT_PROBS]
        if consistency is not None:
            self.in_keys = [*self.in_keys, keys.EXPERT_NIS, keys.COV_SCALE]
            self.out_keys = [*self.out_keys, keys.COV_SCALE]
        if cov is not None:
            self.wire({cov})

    def wire(self, upstream: set) -> None:
        """Fuse the covariances where a stage before it writes the experts' (``COV_KEYS``); with ``consistency``,
        the stages before it must write the experts' covariance and their NIS (filter experts)."""
        key = next((k for k in COV_KEYS if k in upstream), None)
        if key is not None and self.cov is None:
            self.cov = key
            self.in_keys = [*self.in_keys, key]
            self.out_keys = [*self.out_keys, keys.FUSED_COV]
        if self.consistency is not None and (self.cov is None or keys.EXPERT_NIS not in upstream):
            raise ValueError("covariance consistency needs experts that carry a covariance and write their NIS "
                             f"{keys.EXPERT_NIS} (filter experts, immnet.stages.filtering); the stages before "
                             "this Fuse write neither or one")

    def for_experts_alone(self) -> "Fuse":
        return self if self.per_expert else Fuse(self.model_set, per_expert=True, cov=self.cov)

    def carry_spec(self, batch: int, experts_alone: bool = False, dtype=torch.float32, device=None) -> dict:
        """The step's memory, zero before a track starts: ``x``, ``x_{t-2}``, the experts' priors, ``z_{t-1}``."""
        lead = (batch, self.n_experts) if experts_alone else (batch,)
        scale = {} if self.consistency is None else {keys.COV_SCALE: torch.ones(batch, dtype=dtype, device=device)}
        return scale | {
            keys.FUSED: torch.zeros(*lead, 9, dtype=dtype, device=device),
            keys.PREV_FUSED: torch.zeros(*lead, 9, dtype=dtype, device=device),
            keys.PREV_EXPERT_PRIOR: torch.zeros(batch, self.n_experts, 9, dtype=dtype, device=device),
            keys.PREV_MEASUREMENT: torch.zeros(*lead, 3, dtype=dtype, device=device),
        }

    def start_carry(self, carry, z: torch.Tensor, x: torch.Tensor, second: bool) -> dict:
        """A starting track's memory: its start estimate ``x`` as the fused state and every expert's
        prior, ``z`` as the previous measurement, and as ``x_{t-2}`` the first scan's estimate; the reported
        covariance's scale back at 1 (``consistency``)."""
        scale = {} if self.consistency is None else {keys.COV_SCALE: torch.ones_like(z[..., 0])}
        return scale | {
            keys.PREV_FUSED: carry.get(keys.FUSED) if second else x,
            keys.FUSED: x,
            keys.PREV_EXPERT_PRIOR: per_expert(x, self.n_experts).clone(),
            keys.PREV_MEASUREMENT: z,
        }

    def covariance(self, td, fused: torch.Tensor) -> torch.Tensor | None:
        """The fused covariance ``P_t`` of the experts' posteriors and covariances in ``td`` around ``fused``
        (module doc), or None where this stage fuses none. Experts alone: each expert's own ``[B, M, 9, 9]``."""
        if self.cov is None:
            return None
        cov = td.get(self.cov)
        if self.cov == keys.EXPERT_AUG_COV:
            cov = cov[..., :9, :9]
        if self.per_expert:
            return cov
        weights = block_weights(td.get(keys.EXPERT_PROBS).to(cov.dtype), cov.shape[-1], self.groups)
        return moment_match(weights, td.get(keys.EXPERT_POST), fused, cov)

    def consistency_scale(self, scale: torch.Tensor, mu: torch.Tensor, nis: torch.Tensor, has_z: torch.Tensor):
        """The next scale of the reported covariance ``[B]`` (module doc) from the previous one ``[B]``, the mode
        probabilities ``mu [B, M]``, the experts' NIS ``[B, M]`` and whether this scan has a detection ``[B, 1]``.
        An estimator of the output, not a learned part: no gradient flows through it."""
        mu = mu if mu.dim() == 2 else axis_probs(mu, self.groups).mean(-2)  # per group: the mean over the axes
        seen = ((mu * nis).sum(-1) / 3.0).clamp(max=10.0).detach()
        a = self.consistency
        return torch.where(has_z.reshape(-1), (1.0 - a) * scale + a * seen, scale)

    def forward(self, td):
        post = td.get(keys.EXPERT_POST)
        if self.per_expert:
            fused = post
        else:
            mu = td.get(keys.EXPERT_PROBS)
            fused = (coordinate_weights(mu, post.shape[-1], self.groups) * post).sum(1)
        fused_cov = self.covariance(td, fused)
        z = td.get(keys.MEASUREMENT)
        has_z = measured(z)
        if self.consistency is not None:
            td.set(keys.COV_SCALE, self.consistency_scale(td.get(keys.COV_SCALE), mu, td.get(keys.EXPERT_NIS), has_z))
        z_next = torch.where(has_z, z, fused[..., POS_VIEW])
        td.set(keys.PREV_FUSED, td.get(keys.FUSED))
        td.set(keys.PREV_EXPERT_PRIOR, td.get(keys.EXPERT_PRIOR))
        td.set(keys.PREV_MEASUREMENT, z_next)
        td.set(keys.FUSED, fused)
        if fused_cov is not None:
            td.set(keys.FUSED_COV, fused_cov)
        return td
