"""Stage 5, fuse: ``x_t = sum_i mu_t^(i) x_{t|t}^(i)``, and the step's memory moves on one scan.

The fused estimate it replaces becomes ``x_{t-2|t-2}`` for the next step's F3, the experts' priors
become ``x_{t-1|t-2}^(i)`` for F4, and ``z_t`` (or, when missing, the fused position) becomes
``z_{t-1}`` for F1. Where the experts carry a covariance it also fuses the covariances (moment matching,
the IMM's combination),

    P_t = sum_i mu^(i) (P^(i) + (x^(i) - x_t)(x^(i) - x_t)^T),

``P^(i)`` the analytic gain's ``("expert", "cov")`` ``[B, M, 9, 9]``, or the 9x9 state block of a filter
expert's posterior covariance of ``[x, w]``, ``("expert", "aug_cov")`` ``[B, M, 10, 10]``. The paper's
KalmanNet experts (a gain only) carry none: then there is no fused covariance.

``per_expert=True`` is stage-1 training: each expert runs alone, its own posterior is its fused
estimate (``[B, M, 9]``, its covariance its own) and no mode probabilities are needed. ``cov`` (the key of
the experts' covariances; ``wire``d on where a stage before it writes one) fuses them too.
"""

from __future__ import annotations

import torch

from immnet import keys
from immnet.motion import POS
from immnet.stages.base import Stage, measured

COV_KEYS = (keys.EXPERT_COV, keys.EXPERT_AUG_COV)
"""The experts' covariances ``Fuse`` fuses, first found first: the analytic gain's, the filter experts'."""


def moment_match(mu: torch.Tensor, post: torch.Tensor, fused: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    """``sum_i mu_i (P_i + d_i d_i^T)``, ``d_i = x_i - x``: weights ``mu [B, M]``, posteriors ``post [B, M, 9]``,
    their mean ``fused [B, 9]``, covariances ``cov [B, M, 9, 9]``; in ``cov``'s dtype."""
    d = (post - fused.unsqueeze(1)).to(cov.dtype)
    spread = cov + d.unsqueeze(-1) * d.unsqueeze(-2)
    return (mu.to(cov.dtype)[..., None, None] * spread).sum(1)


class Fuse(Stage):
    in_keys = [keys.EXPERT_POST, keys.EXPERT_PROBS, keys.FUSED, keys.EXPERT_PRIOR, keys.MEASUREMENT]
    out_keys = [keys.FUSED, keys.PREV_FUSED, keys.PREV_EXPERT_PRIOR, keys.PREV_MEASUREMENT]

    def __init__(self, model_set=None, per_expert: bool = False, cov=None):
        """``cov``: the key of the experts' covariances to fuse (one of ``COV_KEYS``), or None (as ``wire`` finds)."""
        super().__init__(model_set)
        self.per_expert = per_expert
        self.cov = None
        if per_expert:
            self.in_keys = [k for k in self.in_keys if k != keys.EXPERT_PROBS]
        if cov is not None:
            self.wire({cov})

    def wire(self, upstream: set) -> None:
        """Fuse the covariances where a stage before it writes the experts' (``COV_KEYS``)."""
        key = next((k for k in COV_KEYS if k in upstream), None)
        if key is not None and self.cov is None:
            self.cov = key
            self.in_keys = [*self.in_keys, key]
            self.out_keys = [*self.out_keys, keys.FUSED_COV]

    def for_experts_alone(self) -> "Fuse":
        return self if self.per_expert else Fuse(self.model_set, per_expert=True, cov=self.cov)

    def carry_spec(self, batch: int, experts_alone: bool = False, dtype=torch.float32, device=None) -> dict:
        """The step's memory, zero before a track starts: ``x``, ``x_{t-2}``, the experts' priors, ``z_{t-1}``."""
        lead = (batch, self.n_experts) if experts_alone else (batch,)
        return {
            keys.FUSED: torch.zeros(*lead, 9, dtype=dtype, device=device),
            keys.PREV_FUSED: torch.zeros(*lead, 9, dtype=dtype, device=device),
            keys.PREV_EXPERT_PRIOR: torch.zeros(batch, self.n_experts, 9, dtype=dtype, device=device),
            keys.PREV_MEASUREMENT: torch.zeros(*lead, 3, dtype=dtype, device=device),
        }

    def start_carry(self, carry, z: torch.Tensor, x: torch.Tensor, second: bool) -> dict:
        """A starting track's memory: its start estimate ``x`` as the fused state and every expert's
        prior, ``z`` as the previous measurement, and as ``x_{t-2}`` the first scan's estimate."""
        return {
            keys.PREV_FUSED: carry.get(keys.FUSED) if second else x,
            keys.FUSED: x,
            keys.PREV_EXPERT_PRIOR: (x if x.dim() == 3 else x.unsqueeze(1).expand(-1, self.n_experts, -1)).clone(),
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
        return moment_match(td.get(keys.EXPERT_PROBS), td.get(keys.EXPERT_POST), fused, cov)

    def forward(self, td):
        post = td.get(keys.EXPERT_POST)
        if self.per_expert:
            fused = post
        else:
            mu = td.get(keys.EXPERT_PROBS)
            fused = (mu.unsqueeze(-1) * post).sum(1)
        fused_cov = self.covariance(td, fused)
        z = td.get(keys.MEASUREMENT)
        z_next = torch.where(measured(z), z, fused[..., list(POS)])
        td.set(keys.PREV_FUSED, td.get(keys.FUSED))
        td.set(keys.PREV_EXPERT_PRIOR, td.get(keys.EXPERT_PRIOR))
        td.set(keys.PREV_MEASUREMENT, z_next)
        td.set(keys.FUSED, fused)
        if fused_cov is not None:
            td.set(keys.FUSED_COV, fused_cov)
        return td
