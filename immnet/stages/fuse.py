"""Stage 5, fuse: ``x_t = sum_i mu_t^(i) x_{t|t}^(i)``, and the step's memory moves on one scan.

The fused estimate it replaces becomes ``x_{t-2|t-2}`` for the next step's F3, the experts' priors
become ``x_{t-1|t-2}^(i)`` for F4, and ``z_t`` (or, when missing, the fused position) becomes
``z_{t-1}`` for F1. With the analytic gain it also fuses the covariances,
``P_t = sum_i mu^(i) (P^(i) + (x^(i) - x)(x^(i) - x)^T)``.

``per_expert=True`` is stage-1 training: each expert runs alone, its own posterior is its fused
estimate (``[B, M, 9]``) and no mode probabilities are needed. ``cov=True`` (``wire``d on where the
gain writes the experts' covariances, ``("expert", "cov")``) fuses them too.
"""

from __future__ import annotations

import torch

from immnet import keys
from immnet.motion import POS
from immnet.stages.base import Stage, measured


class Fuse(Stage):
    in_keys = [keys.EXPERT_POST, keys.EXPERT_PROBS, keys.FUSED, keys.EXPERT_PRIOR, keys.MEASUREMENT]
    out_keys = [keys.FUSED, keys.PREV_FUSED, keys.PREV_EXPERT_PRIOR, keys.PREV_MEASUREMENT]

    def __init__(self, model_set=None, per_expert: bool = False, cov: bool = False):
        super().__init__(model_set)
        self.per_expert = per_expert
        self.cov = False
        if per_expert:
            self.in_keys = [k for k in self.in_keys if k != keys.EXPERT_PROBS]
        if cov:
            self.wire({keys.EXPERT_COV})

    def wire(self, upstream: set) -> None:
        """Fuse the covariances where the gain writes the experts' (``("expert", "cov")``)."""
        if keys.EXPERT_COV in upstream and not self.cov:
            self.cov = True
            self.in_keys = [*self.in_keys, keys.EXPERT_COV]
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

    def forward(self, td):
        post = td.get(keys.EXPERT_POST)
        cov = td.get(keys.EXPERT_COV) if self.cov else None
        if self.per_expert:
            fused, fused_cov = post, cov
        else:
            mu = td.get(keys.EXPERT_PROBS)
            fused = (mu.unsqueeze(-1) * post).sum(1)
            if cov is not None:
                d = (post - fused.unsqueeze(1)).to(cov.dtype)
                spread = cov + d.unsqueeze(-1) * d.unsqueeze(-2)
                fused_cov = (mu.to(cov.dtype)[..., None, None] * spread).sum(1)
        z = td.get(keys.MEASUREMENT)
        z_next = torch.where(measured(z), z, fused[..., list(POS)])
        td.set(keys.PREV_FUSED, td.get(keys.FUSED))
        td.set(keys.PREV_EXPERT_PRIOR, td.get(keys.EXPERT_PRIOR))
        td.set(keys.PREV_MEASUREMENT, z_next)
        td.set(keys.FUSED, fused)
        if cov is not None:
            td.set(keys.FUSED_COV, fused_cov)
        return td
