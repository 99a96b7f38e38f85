"""The IMM core: the Kalman update, the interaction (mixing with onset priors, a Markov or a guarded
transition), the mode update and the combination, batched over tracks and filters. Every tracker's
filters are built from these (``immnet.stages.filtering`` for IMMNet and the model-based IMM-EKF,
``immnet.filters`` for the linear IMMs, the Kalman filter and the bounds)."""

from immnet.imm.adaptive import AdaptiveNoise
from immnet.imm.guard import RangeGuard
from immnet.imm.interaction import (
    combine, entering, mix, mixing_weights, mode_update, onset_priors, transition_matrix,
)
from immnet.imm.kalman import inv3, predict, update

__all__ = [
    "AdaptiveNoise", "RangeGuard", "combine", "entering", "inv3", "mix", "mixing_weights", "mode_update",
    "onset_priors", "predict", "transition_matrix", "update",
]
