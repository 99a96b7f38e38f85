"""Model-based trackers as methods: a single-model Kalman filter and the IMM (docs/spec.md section 3).

Both start from the first measurement (``immnet.filters.imm.initial_state``): position at
``z_0`` with variance ``r^2`` (the filter's assumed ``r``), zero velocity and acceleration with
standard deviations 300 m/s and 10 m/s^2 on every axis. At ``t = 0`` the output is that state; a
track whose first scans are missed has no estimate (NaN) until its first detection
(``immnet.filters.base.output``).

Both take any interval before each scan (``immnet.data.times.scan_intervals``, docs/baselines.md): where every
track's every interval is one value, ``F`` and ``Q`` are built once from it (the fixed-interval fast paths);
else per track and scan, ``[B, T, M, 9, 9]``, from the motion models' tensor ``dt``, for the core's scan loop.
"""

from __future__ import annotations

import copy
import math
from typing import Sequence

import torch
from tensordict import TensorDict

from immnet import keys
from immnet.filters.base import Method, as_dtype, data_mode_probs, interval_or_intervals, output
from immnet.filters.imm import ACC_STD, VEL_STD, first_detection, imm_filter, initial_state
from immnet.imm.interaction import transition_matrix
from immnet.imm.kalman import check_robust, check_vz_std
from immnet.imm.measurement import MODEL_BASED, Isotropic, PerDetection, Polar, ToldStd, measurement_model
from immnet.imm.reacquire import Reacquire, Restarts
from immnet.motion import ModelSet, Modes, MotionModel, coupling, instantiate


def _non_negative(name: str, value) -> None:
    """A ValueError unless ``value`` (a number or a list of them) is finite and >= 0, naming ``name``."""
    items = value if isinstance(value, (list, tuple)) else [value]
    try:
        ok = all(math.isfinite(float(v)) and float(v) >= 0 for v in items)
    except (TypeError, ValueError):  # not a number: float()'s own message would not name the setting
        ok = False
    if not ok:
        raise ValueError(f"{name} must be finite and >= 0, got {value!r}")


ISOTROPIC = (Isotropic, ToldStd)
"""The measurement models of a filter with one ``r`` per track: a number or ``"data"`` (each track's own ``r``)."""


def check_sigma_q(sigma_q, n_models: int) -> float | list[float]:
    """``sigma_q``, checked: one for every model or one per model."""
    _non_negative("sigma_q", sigma_q)
    if isinstance(sigma_q, (list, tuple)) and len(sigma_q) != n_models:
        raise ValueError(f"sigma_q has {len(sigma_q)} values for {n_models} models")
    return [float(v) for v in sigma_q] if isinstance(sigma_q, (list, tuple)) else float(sigma_q)


def variance(r: float | torch.Tensor, dtype, device) -> torch.Tensor:
    """``r^2`` as a tensor (a number squared in float64 first, as the fixed-``r`` filters always have)."""
    if isinstance(r, torch.Tensor):
        return r * r
    return torch.tensor(r**2, dtype=dtype, device=device)


def _linear_network(name: str, model_set: ModelSet, sigma_q, r, p_stay: float | None, dt: float, dtype,
                    modes: Modes = Modes.JOINT, robust: float | None = None, reacquire=None, vz_std=None):
    """A linear model set's filters as IMMNet with nothing learned (``IMMTracker.network``); ``modes``: ``IMMNet``'s
    (per axis: ``PerAxisIMMTracker.network``). ``p_stay`` None (a method given a full transition matrix): a
    ValueError naming the method ``name``."""
    from immnet.stages.network import IMMNet

    if p_stay is None:
        raise ValueError(f"{name}: a full transition matrix is not IMMNet's p_stay (one staying probability)")

    gain = {"class_path": "immnet.stages.filtering.FilterGain", "init_args": {
        "model_noise": sigma_q, "r": r, "interaction": "imm", "onset": False, "start_acc_std": ACC_STD}}
    if robust is not None:
        gain["init_args"]["robust"] = robust
    if reacquire is not None:
        gain["init_args"]["reacquire"] = reacquire.to_config()
    if vz_std is not None:
        gain["init_args"]["start_vz_std"] = vz_std
    bayes = {"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"from_experts": True}}
    net = IMMNet(model_set=model_set, gain=gain, classifier=bayes, dt=dt, p_stay=p_stay, start_detections=1,
                 modes=modes)
    return net.to(dtype).eval()


class _ModelSetIMM(Method):
    """What the IMMs over a model set (``IMMTracker``, ``PerAxisIMMTracker``) hold alike: the ``ModelSet`` of
    ``model_set``, the measurement model of ``r`` (one of ``takes``, ``measurement_model``'s), ``sigma_q`` checked
    (``check_sigma_q``), the transition matrix ``Pi`` of ``p_stay`` (and ``_p_stay``, IMMNet's for ``network()``:
    None for a full matrix), the dtype, ``name``, ``return_cov`` and Huber's ``robust``."""

    any_interval = True

    build_options = {"return_cov": False}

    def __init__(self, model_set, r, sigma_q, p_stay, dtype, name: str, return_cov: bool, robust,
                 takes: tuple[type, ...] = MODEL_BASED):
        self.model_set = ModelSet.from_config(model_set)
        M = len(self.model_set)
        self.measurement = measurement_model(r, takes)
        self.r, self.needs, self.sigma_q = r, self.measurement.needs, check_sigma_q(sigma_q, M)
        self.Pi = transition_matrix(p_stay, M)
        self._p_stay = float(p_stay) if isinstance(p_stay, (int, float)) else None  # a full matrix: None
        self.dtype = as_dtype(dtype)
        self.name = name
        self.return_cov = return_cov
        self.robust = check_robust(robust)

    def scaled(self, factor: float):
        """A copy whose process noise is ``factor`` times this one's (every model's ``sigma_q``); the rest shared."""
        out = copy.copy(self)
        out.sigma_q = [v * factor for v in self.sigma_q] if isinstance(self.sigma_q, list) else self.sigma_q * factor
        return out


class IMMTracker(_ModelSetIMM):
    """The standard IMM over a model set.

    ``model_set``: a YAML path, a list of ``class_path`` entries or a ``ModelSet``; ``r``: the
    filter's assumed measurement std (m); ``sigma_q``: process-noise scale, one for all models or
    one per model; ``p_stay``: the Markov chain's staying probability (the rest spread evenly), or
    a full row-stochastic matrix ``[M, M]``; ``mu0``: initial mode probabilities (uniform if None).
    ``track`` gives ``state``, ``mode_probs`` over data modes and, with ``return_experts``, the
    experts' posteriors ``("expert", "post") [B, T, M, 9]`` and probabilities ``("mode", "probs")``.
    ``modes``: one set of mode probabilities for the whole state (``"joint"``, the IMM) or one per group of
    coordinates, ``"axis"`` or ``"channel"`` (the horizontal plane and the vertical, each an IMM of its own over the
    same models: ``immnet.motion.MODE_GROUPS``, docs/core.md "Modes per group"); a grouped IMM tracks with its
    ``network()`` (IMMNet's step with nothing learned) and gives each group's probabilities, ``("mode", "probs")
    [B, T, G, M]``, and the data modes of the axes' mean.
    ``compile``: run the step through ``torch.compile`` (``imm_filter(compile=True)``; seconds to compile
    on first use, then several times faster on CPU for one track or thousands; fixed intervals only).

    ``r`` is the measurement model (``immnet.imm.measurement``): a number or ``"data"`` (isotropic, ``r`` m or each
    track's own), ``"detection"`` (each detection's covariance, the batch's ``meas_cov [B, T, 3, 3]``: ``r^2 I`` there
    gives the isotropic filter's numbers bit for bit) or ``{sigma_range, sigma_azimuth_deg, sigma_elevation_deg}``
    (the plots themselves, an extended Kalman filter in polar coordinates about the radar at the origin). A track
    starts with its first detection's covariance. ``robust``: Huber's ``k`` (``immnet.imm.kalman``'s module doc: an
    innovation beyond ``k`` standard deviations moves the state by ``k`` of them, and the mode update weighs it by
    Huber's density), None: off. ``reacquire``: re-acquisition (``immnet.imm.reacquire.Reacquire``, its fields as a dict,
    True its defaults; None: off): after ``scans`` consecutive detections each beyond ``gate`` (``d^2``) of every filter
    and within ``speed`` of the one before, the track restarts at the last as at its first detection; a Cartesian ``r``.
    ``vz_std``: a prior on a track's vertical speed at its start, ``N(0, vz_std^2)`` m/s (``immnet.imm.kalman.
    start_state``; aircraft climb and descend at a few m/s where one plot says nothing of the speed), None: off.
    The last five are the joint IMM's (``modes="joint"``).
    """

    def __init__(
        self,
        model_set,
        r: float | str,
        sigma_q: float | Sequence[float],
        p_stay: float | Sequence[Sequence[float]] = 0.8,
        mu0: Sequence[float] | None = None,
        dtype="float64",
        name: str = "imm",
        return_experts: bool = False,
        compile: bool = False,
        return_cov: bool = False,
        modes: str = "joint",
        robust: float | None = None,
        reacquire: Reacquire | dict | bool | None = None,
        vz_std: float | None = None,
    ):
        super().__init__(model_set, r, sigma_q, p_stay, dtype, name, return_cov, robust)
        self.modes = Modes.parse(modes)
        groups = self.modes.groups
        self._step_net = None  # the network a grouped IMM tracks with (_track_by_step)
        if groups is not None and (coupled := coupling(self.model_set, groups)):
            raise ValueError(f"{name}: modes per {modes} need models whose F is block diagonal per group; "
                             f"{coupled} couple the groups")
        M = len(self.model_set)
        shapes = {tuple(m.F(1.0).shape) for m in self.model_set}
        if len(shapes) != 1 or any(len(s) != 2 or s[0] != s[1] for s in shapes):
            raise ValueError(f"model set {self.model_set} mixes state dimensions: F shapes {sorted(shapes)}")
        moving = [m.name for m in self.model_set if m.state_dependent]
        if moving:
            raise ValueError(f"the IMM needs a constant F per model; {moving} are state-dependent (IMMNet experts only)")
        isotropic = isinstance(self.measurement, ISOTROPIC)
        self.reacquire = Reacquire.from_config(reacquire)
        self.vz_std = check_vz_std(vz_std)
        if groups is not None and not (isotropic and self.robust is None and self.reacquire is None
                                       and self.vz_std is None):
            raise ValueError(f"{name}: modes per {modes} track with IMMNet's step, which takes an isotropic r, no "
                             f"robust update, no re-acquisition and no vz_std")
        if self.reacquire is not None and isinstance(self.measurement, Polar):
            raise ValueError(f"{name}: re-acquisition takes a Cartesian measurement model (a number, 'data' or "
                             f"'detection'), not the polar one")
        self.mu0 = torch.as_tensor([1.0 / M] * M if mu0 is None else mu0, dtype=torch.float64)  # uniform by default
        if self.mu0.shape != (M,):
            raise ValueError(f"mu0 must have one probability per model ({M}), got shape {tuple(self.mu0.shape)}")
        if (self.mu0 < 0).any() or abs(float(self.mu0.sum()) - 1.0) > 1e-6:
            raise ValueError(f"mu0 must be non-negative and sum to 1, got {self.mu0.tolist()}")
        self.return_experts = return_experts
        self.compile = compile

    def scaled(self, factor: float) -> "IMMTracker":
        """``_ModelSetIMM.scaled``, its grouped step network (``_track_by_step``) built again for the new noise."""
        out = super().scaled(factor)
        out._step_net = None
        return out

    def network(self, dt: float = 1.0):
        """This IMM as IMMNet with nothing learned (docs/core.md, "Every tracker as a configuration"): filter
        experts of the model set with each model's own process noise (``FilterGain(model_noise=sigma_q)``), the
        assumed ``r``, the IMM's mix without onset priors, a start from the first detection with the spec's start
        covariance (``start_detections=1``, ``start_acc_std`` 10 m/s^2, velocity 300 m/s) and the IMM's Bayesian
        mode update, ``p_stay`` set once; an ``IMMNet`` in this method's dtype, ``eval``. It filters what
        ``track`` filters, to float64 rounding, each track from its first detection on (both start it there).
        With ``r: data`` the filter experts are told each track's ``r`` (``FilterGain(r="data")``): give it to
        ``rollout(..., r=batch["r"])``; with ``r: detection`` each detection's covariance (``FilterGain(r="detection")``):
        ``rollout(..., meas_cov=net.told_cov(batch))``; ``robust``: the experts' Huber update (``FilterGain(robust=k)``).
        A ValueError where this IMM is not such a configuration: a polar measurement model, a full transition matrix, a
        non-uniform ``mu0``."""
        if isinstance(self.measurement, Polar):
            raise ValueError(f"{self.name}: IMMNet's filter experts take an isotropic r or each detection's covariance, "
                             f"this IMM has the polar model r={self.r!r}")
        if not torch.allclose(self.mu0, torch.full_like(self.mu0, 1.0 / len(self.mu0))):
            raise ValueError(f"{self.name}: IMMNet starts a track with uniform mode probabilities, mu0 is {self.mu0.tolist()}")
        return _linear_network(self.name, self.model_set, self.sigma_q, self.r, self._p_stay, dt, self.dtype,
                               self.modes, self.robust, self.reacquire, self.vz_std)

    def matrices(self, dt, device=None):
        """``F, Q`` of the experts, ``Pi``, ``mu0``: ``F, Q`` ``[M, 9, 9]`` for a float ``dt``, ``[..., M, 9, 9]``
        for a tensor of intervals ``dt [...]`` (``[B, T]``: one per track and scan)."""
        F = self.model_set.F(dt, dtype=self.dtype, device=device)
        Q = self.model_set.Q(self.sigma_q, dt, dtype=self.dtype, device=device)
        return F, Q, self.Pi.to(self.dtype).to(device), self.mu0.to(self.dtype).to(device)

    def track(self, batch: TensorDict) -> TensorDict:
        self.check(batch)
        if self.modes is not Modes.JOINT:
            return self._track_by_step(batch)
        z = batch[keys.MEASUREMENTS].to(self.dtype)
        intervals = interval_or_intervals(batch, self.dtype, z.device)
        F, Q, Pi, mu0 = self.matrices(intervals, z.device)
        first = first_detection(z)
        model, rows = self.measurement, torch.arange(len(first), device=z.device)
        robust, measure, R = self.robust, None, None
        if isinstance(model, Polar):  # the EKF's update (Huber's k its own); a track starts with its converted plot
            sig0 = model.sigmas(z.shape[:2], z.dtype, z.device)[rows, first]
            x0, P0 = initial_state(z, None, cov0=model.initial_cov(z[rows, first], sig0), vz_std=self.vz_std)
            robust, measure = None, model.measure(z, self.robust)
        elif isinstance(model, PerDetection):
            R = model.R(batch, self.dtype, z.device)
            x0, P0 = initial_state(z, None, cov0=R[rows, first], vz_std=self.vz_std)
        else:
            r = model.std(batch, self.dtype, z.device)
            x0, P0 = initial_state(z, r, vz_std=self.vz_std)
            R = variance(r, self.dtype, z.device)
        reacquire = None if self.reacquire is None else Restarts(self.reacquire, intervals, VEL_STD, ACC_STD, mu0,
                                                                  self.vz_std)  # restarting as a track starts
        states, probs, experts, *cov = imm_filter(z, x0, P0, F, Q, R, Pi, mu0, self.return_experts,
                                                  compile=self.compile, return_cov=self.return_cov, start=first,
                                                  robust=robust, reacquire=reacquire, measure=measure)
        extra = {keys.MODE_PROBS: data_mode_probs(probs, self.model_set.modes), keys.STATE_COV: cov[0] if cov else None,
                 keys.EXPERT_POST: experts, keys.EXPERT_PROBS: probs if self.return_experts else None}  # None: left out
        return output(states, extra, measurements=z)

    @torch.no_grad()
    def _track_by_step(self, batch: TensorDict) -> TensorDict:
        """``track`` of an IMM with modes per group: its ``network()`` over the batch, each track's ``r`` told where
        ``r: data``, each scan's interval where they are not all 1 s."""
        z = batch[keys.MEASUREMENTS].to(self.dtype)
        if self._step_net is None:  # built once: each batch of an evaluation runs the same network
            self._step_net = self.network()
        net = self._step_net.to(z.device)
        intervals = net.intervals_for(batch)
        r = self.measurement.std(batch, self.dtype, z.device) if isinstance(self.measurement, ToldStd) else None
        out, _ = net.rollout(z, intervals=None if intervals is None else intervals.to(self.dtype), r=r,
                             return_cov=self.return_cov)
        probs = out[keys.ROLLOUT_EXPERT_PROBS]
        extra = {keys.MODE_PROBS: net.to_mode_probs(probs), keys.STATE_COV: out[keys.STATE_COV] if self.return_cov else None}
        if self.return_experts:
            extra[keys.EXPERT_POST], extra[keys.EXPERT_PROBS] = out[keys.ROLLOUT_EXPERT_POST], probs
        return output(out[keys.STATE], extra, measurements=z)


class KalmanFilterTracker(IMMTracker):
    """A Kalman filter with one motion model, noise ``sigma_q`` and assumed measurement std ``r`` (a number or
    ``"data"``): the IMM of that one model (``IMMTracker``: its ``robust``, ``reacquire`` and ``network()``), whose
    output has no ``mode_probs`` (one model, no mode to weigh)."""

    def __init__(self, model: MotionModel | dict, r: float | str, sigma_q: float, dtype="float64",
                 name: str | None = None, return_cov: bool = False, robust: float | None = None, reacquire=None):
        self.model = model if isinstance(model, MotionModel) else instantiate(model)
        measurement_model(r, ISOTROPIC)  # one r per track: no detection's covariance, no polar model
        # one model: Pi = [[1]] whatever p_stay (which IMMNet's interaction holds to (0, 1): network())
        super().__init__(ModelSet([self.model]), r, sigma_q, 0.5, dtype=dtype, name=name or f"kf-{self.model.name}",
                         return_cov=return_cov, robust=robust, reacquire=reacquire)

    def track(self, batch: TensorDict) -> TensorDict:
        return super().track(batch).exclude(keys.MODE_PROBS)
