"""What a stage is: a ``TensorDictModuleBase`` over the key vocabulary of ``immnet.keys``.

Every stage reads the keys it names in ``in_keys`` and writes those in ``out_keys``; a tracker step
is a ``TensorDictSequential`` of five stages (predict, gain, update, classify, fuse). Tensors are
``[B, ...]`` for a fused quantity and ``[B, M, ...]`` for one per expert. In stage-1 training each
expert runs alone on its own trajectories, so the "fused" state is itself ``[B, M, 9]``;
``per_expert`` lets every stage accept both.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModuleBase

from immnet.motion import ModelSet


class Stage(TensorDictModuleBase):
    """A stage built for a model set of ``M`` experts."""

    in_keys: list = []
    out_keys: list = []

    def __init__(self, model_set: ModelSet | None = None):
        super().__init__()
        self.model_set = model_set
        self.n_experts = len(model_set) if model_set is not None else 1


def per_expert(x: torch.Tensor, n_experts: int, event_dims: int = 1) -> torch.Tensor:
    """``[B, *event]`` broadcast to ``[B, M, *event]``; ``[B, M, *event]`` is returned as is."""
    if x.dim() == 1 + event_dims:
        return x.unsqueeze(1).expand(x.shape[0], n_experts, *x.shape[1:])
    return x


def measured(z: torch.Tensor) -> torch.Tensor:
    """Mask of rows holding a measurement (no NaN component), shape ``z.shape[:-1] + (1,)``."""
    return ~torch.isnan(z).any(dim=-1, keepdim=True)
