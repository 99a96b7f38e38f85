"""Stage 1, predict: every expert propagates the previous fused estimate with its own model.

``x_{t|t-1}^(i) = F^(i) x_{t-1|t-1}``  (SPEC.md section 4, step 1).
"""

from __future__ import annotations

import torch

from immnet import keys
from immnet.motion import ModelSet
from immnet.stages.base import Stage, per_expert


class Predict(Stage):
    in_keys = [keys.FUSED]
    out_keys = [keys.EXPERT_PRIOR]

    def __init__(self, model_set: ModelSet, dt: float = 1.0):
        super().__init__(model_set)
        self.register_buffer("F", model_set.F(dt, dtype=torch.float32))

    def forward(self, td):
        x = per_expert(td.get(keys.FUSED), self.n_experts)
        td.set(keys.EXPERT_PRIOR, torch.einsum("mij,bmj->bmi", self.F, x))
        return td
