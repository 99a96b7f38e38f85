"""Stage 1, predict: every expert propagates the previous fused estimate with its own model.

``x_{t|t-1}^(i) = F^(i) x_{t-1|t-1}``  (docs/spec.md section 4, step 1), ``F`` of the nominal ``dt`` or of
the step's interval per track (``("interval")``, where it carries one).

An expert whose transition depends on the state (``AdaptiveTurn``: a coordinated turn at the turn
rate its state implies, ``w = (vx ay - vy ax) / |v_h|^2``, bounded) is propagated in closed form,
``x_{t|t-1}^(i) = F_CT(w^(i)(x_{t-1|t-1})) x_{t-1|t-1}``; the others by their constant ``F^(i)``.
"""

from __future__ import annotations

import torch

from immnet import keys
from immnet.motion import ModelSet, adaptive_ct_propagate
from immnet.stages.base import Stage, per_expert, scan_interval


class Predict(Stage):
    in_keys = [keys.FUSED]
    out_keys = [keys.EXPERT_PRIOR]

    def __init__(self, model_set: ModelSet, dt: float = 1.0):
        super().__init__(model_set)
        self.dt = dt
        self.register_buffer("F", model_set.F(dt, dtype=torch.float32))
        adaptive = [m.state_dependent for m in model_set]
        self.adaptive = any(adaptive)
        if self.adaptive:
            bounds = [m.rate_bounds() if a else (0.0, 0.0) for m, a in zip(model_set, adaptive)]
            self.register_buffer("is_adaptive", torch.tensor(adaptive)[:, None])
            self.register_buffer("w_lo", torch.tensor([b[0] for b in bounds]))
            self.register_buffer("w_hi", torch.tensor([b[1] for b in bounds]))

    def forward(self, td):
        x = per_expert(td.get(keys.FUSED), self.n_experts)
        dt, per_track = scan_interval(td, self.dt)
        if per_track:
            dt = dt.to(x.dtype)
            prior = torch.einsum("bmij,bmj->bmi", self.model_set.F(dt[:, 0], dtype=x.dtype, device=x.device), x)
        else:
            prior = torch.einsum("mij,bmj->bmi", self.F, x)
        if self.adaptive:
            turned = adaptive_ct_propagate(x, self.w_lo.to(x.dtype), self.w_hi.to(x.dtype), dt)
            prior = torch.where(self.is_adaptive, turned, prior)
        td.set(keys.EXPERT_PRIOR, prior)
        return td
