"""Motion models as data: ``F(dt)``, ``Q(sigma_q, dt)``, names and the mode each stands for."""

from immnet.motion.base import ModelSet, MotionModel, instantiate
from immnet.motion.kinds import ConstantAcceleration, ConstantVelocity, CoordinatedTurn
from immnet.motion.models import (
    ACC,
    DEG,
    MODE_NAMES,
    POS,
    VEL,
    ca_matrix,
    ct_matrix,
    cv_matrix,
    measurement_matrix,
    noise_gain,
    process_noise,
)

__all__ = [
    "ACC", "DEG", "MODE_NAMES", "POS", "VEL",
    "ConstantAcceleration", "ConstantVelocity", "CoordinatedTurn", "ModelSet", "MotionModel",
    "ca_matrix", "ct_matrix", "cv_matrix", "instantiate", "measurement_matrix", "noise_gain",
    "process_noise",
]
