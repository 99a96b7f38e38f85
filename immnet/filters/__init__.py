"""Model-based trackers: batched Kalman filter and IMM, the clairvoyant bound, IMM tuning.

Every method has ``name``, ``needs`` and ``track(batch) -> TensorDict[B]`` (``immnet.filters.base``).
"""

from immnet.filters.base import Method, data_mode_probs
from immnet.filters.clairvoyant import ClairvoyantKF, SwitchClairvoyantKF
from immnet.filters.guard import RangeGuard
from immnet.filters.imm import combine, imm_filter, imm_step, initial_state, mix
from immnet.filters.imm_ekf import IMMEKF, altitude_noise_var
from immnet.filters.kalman import inv3, predict, update
from immnet.filters.trackers import IMMTracker, KalmanFilterTracker, transition_matrix

__all__ = [
    "ClairvoyantKF", "IMMEKF", "IMMTracker", "SwitchClairvoyantKF", "KalmanFilterTracker", "Method", "RangeGuard", "altitude_noise_var",
    "combine", "data_mode_probs", "imm_filter", "imm_step", "initial_state", "inv3", "mix", "predict", "transition_matrix", "update",
]
