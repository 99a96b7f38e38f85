"""Model-based trackers: batched Kalman filter and IMM, the clairvoyant bound, IMM tuning.

Every method has ``name``, ``needs`` and ``track(batch) -> TensorDict[B]`` (``immnet.filters.base``).
"""

from immnet.filters.base import Method, data_mode_probs
from immnet.filters.clairvoyant import ClairvoyantKF, SwitchClairvoyantKF
from immnet.imm.guard import RangeGuard
from immnet.filters.imm import imm_filter, initial_state
from immnet.filters.imm_ekf import IMMEKF
from immnet.imm.kalman import inv3, predict, update
from immnet.filters.trackers import IMMTracker, KalmanFilterTracker
from immnet.imm.interaction import combine, mix, transition_matrix

__all__ = [
    "ClairvoyantKF", "IMMEKF", "IMMTracker", "SwitchClairvoyantKF", "KalmanFilterTracker", "Method", "RangeGuard",
    "combine", "data_mode_probs", "imm_filter", "initial_state", "inv3", "mix", "predict", "transition_matrix", "update",
]
