"""IMM-EKF: the IMM a tracking engineer would build from the 3D-LAST generator's statistics, which is
IMMNet with nothing learned.

The paper's IMM variants (``IMMTracker``) are linear: CT at a fixed turn rate, a CA model that must
find each new acceleration through its process noise, and one ``r`` for every track. This method is
told what the data's *statistics* are (docs/spec.md section 2), never a trajectory's truth, and it is
IMMNet's filter experts with their base process noise (``immnet.stages.filtering.FilterGain``) and the
IMM's Bayesian mode update (``immnet.stages.BayesianModeUpdate(from_experts=True)``), run by
``immnet.stages.IMMNet``: the same track start, interaction, filters and mode update as the learned
tracker it is compared with, so that the difference between the two is what learning adds.

* four mode-matched filters over the augmented state ``[x (9), w]`` (``model_set``, by default
  ``configs/model_sets/imm4-adaptive.yaml``: CV, CA, CT+ and CT-); the turn filters are extended
  Kalman filters that estimate their turn rate ``w`` (its Jacobian ``immnet.motion.ct_jacobian``),
  bounded to ``1 <= |w| <= 30`` deg/s in their sign (``TURN_RATE_LIMIT_DEG``, what an aircraft can fly;
  docs/robustness.md);
* the truth's process noise (white acceleration, ``sigma_q`` 0.2 m/s^2 on position and velocity);
  a CA segment's acceleration is constant, a turn's rate too (``rate_noise_deg`` per scan, 0);
* the IMM interaction with the generator's **onset priors** (``immnet.imm.interaction.onset_priors``):
  what enters a filter from another carries the prior of what a switch into it draws anew (into CA,
  the acceleration; into a turn, the turn rate), from ``spec`` (``DataSpec``, 3D-LAST's by default);
* a Markov chain with ``p_stay`` per scan (the rest shared evenly), set once for the interaction and
  the mode update;
* the measurement noise ``r`` estimated per track from the third differences of the altitude
  measurements (``E[(d^3 z)^2] = 20 r^2``), a running mean from a prior ``r0`` worth ``k0`` samples
  (``r`` fixed instead if given);
* IMMNet's track start: the first detection's position, then the differenced velocity at the second
  (docs/immnet.md); no estimate (NaN) before a track's first detection.

With ``guard`` (``immnet.imm.guard.RangeGuard``: ``True`` for the generator's soft range and speed bounds,
or its fields as a dict) the Markov matrix becomes state-dependent per track and source filter
(``configs/methods/imm-ekf-guard.yaml``). With ``adapt`` (``immnet.imm.adaptive.AdaptiveNoise``) each
track's white-acceleration noise is scaled by covariance matching (``configs/methods/imm-ekf-adaptive.yaml``).
``p_stay`` 0.995 was chosen on the dev set (seed 21), among 0.98, 0.99, 0.995, 0.998 and 0.999.
``return_cov``: also ``state_cov [B, T, 9, 9]``, the filters' covariances moment-matched (``IMMNet.rollout``'s).
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

from immnet import keys
from immnet.filters.base import Method, as_dtype, data_mode_probs, interval_or_intervals, output
from immnet.filters.trackers import _non_negative
from immnet.imm.option import is_number
from immnet.motion import DEG, ModelSet
from immnet.stages.network import IMMNet

IMM4 = "configs/model_sets/imm4-adaptive.yaml"


class IMMEKF(Method):
    """IMMNet with nothing learned: filter experts with their base noise and the IMM's mode update (module doc)."""

    any_interval = True  # each scan's interval per track (scan_intervals)

    build_options = {"return_cov": False, "guard": None}

    def __init__(
        self,
        p_stay: float = 0.995,
        sigma_q: float = 0.2,
        r: float | None = None,
        r0: float = 4.0,
        k0: float = 3.0,
        rate_noise_deg: float = 0.0,
        guard=None,
        adapt=None,
        model_set=IMM4,
        spec: dict | None = None,
        dtype="float64",
        name: str = "imm-ekf",
        return_cov: bool = False,
    ):
        for arg, value in (("sigma_q", sigma_q), ("p_stay", p_stay)):  # one number each: float() below
            if not is_number(value):
                raise ValueError(f"{arg} must be one number, got {value!r}")
        _non_negative("sigma_q", sigma_q)
        _non_negative("rate_noise_deg", rate_noise_deg)  # p_stay, r, r0 and k0 are checked by the network's stages
        self.model_set = ModelSet.from_config(model_set)
        noise = (float(sigma_q), float(sigma_q), 0.0, 0.0, float(rate_noise_deg) * DEG)
        self.gain = {"class_path": "immnet.stages.filtering.FilterGain", "init_args": {
            "noise_std": noise, "r0": r0, "k0": k0, "r": r, "interaction": "imm", "adapt": adapt, "spec": spec}}
        self.classifier = {"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"from_experts": True}}
        self.p_stay, self.guard = float(p_stay), guard  # set once, on the network (IMMNet's SET_ONCE)
        self.dtype, self.name = as_dtype(dtype), name
        self.return_cov = return_cov  # state_cov: the filters' covariances fused by moment matching (IMMNet.rollout)
        self._nets: dict = {}
        self.network(1.0)  # every argument checked now, not at the first batch

    def network(self, dt: float = 1.0):
        """The ``IMMNet`` this method is at the sampling interval ``dt`` (in this method's dtype)."""
        if dt not in self._nets:
            net = IMMNet(model_set=self.model_set, gain=self.gain, classifier=self.classifier, dt=dt, p_stay=self.p_stay,
                         guard=self.guard)
            self._nets[dt] = net.to(self.dtype).eval()
        return self._nets[dt]

    @torch.no_grad()
    def track(self, batch: TensorDict) -> TensorDict:
        self.check(batch)
        z = batch[keys.MEASUREMENTS].to(self.dtype)
        dt = interval_or_intervals(batch, self.dtype, z.device)
        one = isinstance(dt, float)  # one for every scan: the network at it; else at 1 s told each scan's interval
        net = self.network(dt if one else 1.0).to(z.device)  # (docs/baselines.md, "Scan intervals")
        out, _ = net.rollout(z, intervals=None if one else dt, return_cov=self.return_cov)
        probs = data_mode_probs(out[keys.ROLLOUT_EXPERT_PROBS], self.model_set.modes)
        cov = out[keys.STATE_COV] if self.return_cov else None
        return output(out[keys.STATE], {keys.MODE_PROBS: probs, keys.STATE_COV: cov}, measurements=z)
