"""Model-based trackers: batched Kalman filter and IMM, the clairvoyant bound, IMM tuning; the methods by name
(``immnet.filters.methods``, ``registry``) and the multi-target tracker over them (``immnet.filters.multi``).

Every method has ``name``, ``needs`` and ``track(batch) -> TensorDict[B]`` (``immnet.filters.base``). The names below
load their modules (torch) when first asked for, so that the registry's names are read without them.
"""

from immnet.lazy import lazy_names

__getattr__, __dir__, __all__ = lazy_names(__name__, {
    "Method": "immnet.filters.base", "data_mode_probs": "immnet.filters.base",
    "ClairvoyantKF": "immnet.filters.clairvoyant", "SwitchClairvoyantKF": "immnet.filters.clairvoyant",
    "RangeGuard": "immnet.imm.guard",
    "imm_filter": "immnet.filters.imm", "initial_state": "immnet.filters.imm",
    "IMMEKF": "immnet.filters.imm_ekf",
    "inv3": "immnet.imm.kalman", "predict": "immnet.imm.kalman", "update": "immnet.imm.kalman",
    "IMMTracker": "immnet.filters.trackers", "KalmanFilterTracker": "immnet.filters.trackers",
    "combine": "immnet.imm.interaction", "mix": "immnet.imm.interaction", "transition_matrix": "immnet.imm.interaction",
})
