"""Motion models as data: ``F(dt)``, ``Q(sigma_q, dt)``, names and the mode each stands for."""

from immnet.motion.base import ModelSet, MotionModel, instantiate
from immnet.motion.kinds import AdaptiveTurn, ConstantAcceleration, ConstantVelocity, CoordinatedTurn
from immnet.motion.models import (
    ACC,
    DEG,
    MODE_NAMES,
    POS,
    TURN_RATE_LIMIT_DEG,
    VEL,
    adaptive_ct_propagate,
    ca_matrix,
    ct_matrix,
    ct_propagate,
    cv_matrix,
    measurement_matrix,
    noise_gain,
    process_noise,
    turn_rate_of,
)

__all__ = [
    "ACC", "AdaptiveTurn", "DEG", "MODE_NAMES", "POS", "TURN_RATE_LIMIT_DEG", "VEL",
    "ConstantAcceleration", "ConstantVelocity", "CoordinatedTurn", "ModelSet", "MotionModel",
    "adaptive_ct_propagate", "ca_matrix", "ct_matrix", "ct_propagate", "cv_matrix", "instantiate",
    "measurement_matrix", "noise_gain", "process_noise", "turn_rate_of",
]
