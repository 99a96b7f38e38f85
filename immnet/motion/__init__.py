"""Motion models as data: ``F(dt)``, ``Q(sigma_q, dt)``, the coordinated turn's map and Jacobian, names and
the mode each stands for."""

from immnet.labels import MODE_LABELS, MODE_NAMES
from immnet.motion.base import ModelSet, MotionModel, instantiate
from immnet.motion.kinds import AdaptiveTurn, ConstantAcceleration, ConstantVelocity, CoordinatedTurn, Singer
from immnet.motion.models import (
    ACC,
    ACC_VIEW,
    AXES,
    AXIS_OF,
    CA,
    CT_NEG,
    CT_POS,
    CV,
    DEG,
    MODE_GROUPS,
    Modes,
    N_MODES,
    N_AUG,
    POS,
    POS_VIEW,
    RATE,
    TURN_ENTRIES,
    TURN_RATE_LIMIT_DEG,
    VEL,
    VEL_VIEW,
    adaptive_ct_propagate,
    ca_matrix,
    ct_jacobian,
    ct_jacobian_entries,
    ct_matrix,
    ct_propagate,
    ct_rate_derivative,
    cv_matrix,
    coupling,
    fits_groups,
    group_members,
    groups_separate,
    measured_groups,
    measurement_matrix,
    noise_gain,
    process_noise,
    singer_block,
    singer_matrix,
    singer_noise,
    turn_rate_of,
)

__all__ = [
    "ACC", "AXES", "AXIS_OF", "AdaptiveTurn", "CA", "CT_NEG", "CT_POS", "CV", "DEG", "MODE_GROUPS", "MODE_LABELS", "MODE_NAMES", "N_AUG", "N_MODES", "POS", "RATE",
    "TURN_ENTRIES", "TURN_RATE_LIMIT_DEG", "VEL", "ct_jacobian", "ct_jacobian_entries", "ct_rate_derivative",
    "ACC_VIEW", "POS_VIEW", "VEL_VIEW",
    "ConstantAcceleration", "ConstantVelocity", "CoordinatedTurn", "ModelSet", "Modes", "MotionModel",
    "adaptive_ct_propagate", "ca_matrix", "coupling", "ct_matrix", "ct_propagate", "cv_matrix", "fits_groups",
    "group_members", "groups_separate", "instantiate", "measured_groups", "measurement_matrix", "noise_gain", "process_noise", "Singer", "singer_block", "singer_matrix", "singer_noise", "turn_rate_of",
]
