"""Stage 3, update: ``x_{t|t}^(i) = x_{t|t-1}^(i) + K^(i) (z_t - H x_{t|t-1}^(i))``.

A missing measurement (NaN) leaves the prior as the posterior: the expert coasts.
"""

from __future__ import annotations

import torch

from immnet import keys
from immnet.motion import POS_VIEW
from immnet.stages.base import Stage, per_expert


def innovation(z: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
    """``z_t - H x_{t|t-1}^(i)`` with NaN measurements giving zero, shape ``[B, M, 3]``."""
    z = per_expert(z, prior.shape[1])
    nu = z - prior[..., POS_VIEW]
    return torch.nan_to_num(nu, nan=0.0)


class Update(Stage):
    in_keys = [keys.MEASUREMENT, keys.EXPERT_PRIOR, keys.EXPERT_GAIN]
    out_keys = [keys.EXPERT_POST]

    def forward(self, td):
        prior = td.get(keys.EXPERT_PRIOR)
        nu = innovation(td.get(keys.MEASUREMENT), prior)
        gain = td.get(keys.EXPERT_GAIN)
        td.set(keys.EXPERT_POST, prior + (gain @ nu.unsqueeze(-1)).squeeze(-1))
        return td
