"""IMMNet: one tracker step as a ``TensorDictSequential`` of its stages, and its rollout over time.

    [track start] -> predict -> gain -> update -> classify -> fuse -> [join starts]      (docs/spec.md section 4)

(filter experts: their interaction before the predict, a stage of its own).

Every component is chosen by configuration (``class_path`` / ``init_args``); the model set is a
YAML list of motion models. A track starts from two measurements: at its first scan the estimate
is ``[z_0, 0, 0]``, at its second ``[z_1, (z_1 - z_0)/dt, 0]`` (position and differenced
velocity), and from its third scan on the learned step runs. Tracks start independently: the carry
holds each track's age, and the start is part of the step (``TrackStart`` first, ``JoinStarts`` last:
``immnet.stages.start``), so one code path, the step, serves batched rollouts and the streaming ``Tracker``.
The carry is what the stages declare they carry (``Stage.carry_spec``, ``Stage.start_carry``;
docs/stages.md), and each stage is told what the stages before it write (``Stage.wire``).
"""

from __future__ import annotations

import functools
import inspect
import math
from typing import Callable

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from tensordict.utils import unravel_key

from immnet import keys
from immnet.choice import Choice, spelled
from immnet.config import import_class
from immnet.data.times import scan_intervals
from immnet.motion import N_MODES, POS_VIEW, ModelSet, Modes, coupling
from immnet.stages.base import Stage, axis_probs, track_where
from immnet.stages.classify import ModeUpdate
from immnet.stages.fuse import Fuse
from immnet.stages.gain import Gain
from immnet.stages.start import JoinStarts, TrackStart

DEFAULT_GAIN = {"class_path": "immnet.stages.KalmanNetGain"}
DEFAULT_CLASSIFIER = {"class_path": "immnet.stages.TransformerClassifier"}
SET_ONCE = ("p_stay", "guard", "modes")
"""Settings the interaction and the mode update must agree on: ``IMMNet``'s own arguments, handed to each
component that takes them (docs/configs.md, "IMMNet's configuration")."""



class Likelihood(Choice):
    """What a scan's measurement log-likelihood is taken under (``IMMNet.predictive_loglik``), the setting a bank of
    networks weighs its members by (``immnet.tracking.bank``, ``likelihood``) and a rollout's ``return_loglik``:
    ``FILTER`` (``"filter"``) the filter's prediction; ``REPORTED`` (``"reported"``) the track's as the network
    reports it (``reported=True``: moved by its output correction of the scan before)."""

    FILTER = "filter"
    REPORTED = "reported"

    @classmethod
    def refusal(cls, value) -> str:
        return f"a bank's likelihood is one of {', '.join(cls.spellings())}, got {value!r}"


def loglik_asked(return_loglik) -> Likelihood | None:
    """A rollout's ``return_loglik`` as the likelihood asked for: False (or None) none, True the filter's, else a
    ``Likelihood`` or its spelling; anything else a ValueError in one line."""
    if return_loglik is None or return_loglik is False:
        return None
    if return_loglik is True:
        return Likelihood.FILTER
    kind = Likelihood.lookup(return_loglik)
    if kind is None:
        raise ValueError(f"return_loglik must be False, True or one of {Likelihood.spellings()}, got {return_loglik!r}")
    return kind


Component = Callable[[ModelSet, float], Stage]
"""A stage to be built for the model set and interval: a ``class_path`` / ``init_args`` mapping, or what
LightningCLI (jsonargparse) makes of one for a ``Callable[[ModelSet, float], Stage]`` argument."""


def component_config(component) -> dict:
    """``{"class_path", "init_args"}`` of a component given as a mapping or as the callable jsonargparse
    builds for ``Component`` (a ``functools.partial`` of the class's instantiation); a ValueError otherwise."""
    if isinstance(component, dict):
        if "class_path" not in component:
            raise ValueError(f"a component needs a 'class_path', got {component!r}")
        return {"class_path": component["class_path"], "init_args": dict(component.get("init_args") or {})}
    if isinstance(component, functools.partial):
        classes = [a for a in (component.func, *component.args) if inspect.isclass(a)]
        if classes:
            cls = classes[-1]
            return {"class_path": f"{cls.__module__}.{cls.__qualname__}", "init_args": dict(component.keywords)}
    raise ValueError(f"a component is a class_path / init_args mapping, got {component!r}")


NET_ARGUMENTS = ("model_set", "gain", "classifier", "dt", "p_stay", "guard", "interval_range", "cov_consistency",
                 "start_detections", "modes", "correction")
"""``IMMNet``'s arguments: what a ``net`` config (a checkpoint's hyper-parameters) may hold."""


def net_arguments(config: dict | None, saved: bool = False) -> dict:
    """``IMMNet``'s keyword arguments from a ``net`` config: its arguments themselves (``model_set``, ``gain``,
    ...), or the ``class_path: immnet.stages.IMMNet`` / ``init_args`` form LightningCLI writes; an argument IMMNet
    does not take (``NET_ARGUMENTS``) is refused in one line. ``saved``: a checkpoint's, whose ``p_stay`` or guard
    that no component takes is dropped (written before ``IMMNet`` refused one, which then changed nothing)."""
    config = dict(config or {})
    if "class_path" in config:
        cls = import_class(config["class_path"])
        if not (inspect.isclass(cls) and issubclass(cls, IMMNet)):
            raise ValueError(f"net must be an immnet.stages.IMMNet, got class_path {config['class_path']!r}")
        config = dict(config.get("init_args") or {})
    unknown = sorted(set(config) - set(NET_ARGUMENTS))
    if unknown:
        raise ValueError(f"the network's configuration holds {', '.join(map(repr, unknown))}, which IMMNet does not "
                         f"take (its arguments: {', '.join(NET_ARGUMENTS)})")
    if saved:
        roles = {"gain": (DEFAULT_GAIN, Gain), "classifier": (DEFAULT_CLASSIFIER, ModeUpdate),
                 "correction": (None, Stage)}
        taken = _taken(import_class(component_config(config.get(name) or default)["class_path"], role)
                       for name, (default, role) in roles.items() if config.get(name) or default)
        config = {k: v for k, v in config.items() if k not in ("p_stay", "guard") or k in taken}
    return config


def build_component(component, model_set: ModelSet, dt: float, settings: dict, role: type = Stage) -> Stage:
    """The stage ``component`` names (of a ``role``: ``Gain``, ``ModeUpdate``, or any ``Stage``), for ``model_set`` and
    ``dt``, with the ``settings`` (``SET_ONCE``, set on ``IMMNet``) in place of the component's own values wherever
    its class takes them (its ``Stage.shared``)."""
    config = component_config(component)
    cls = import_class(config["class_path"], role)
    args = dict(config["init_args"]) | {name: value for name, value in settings.items() if name in cls.shared}
    return cls(model_set=model_set, dt=dt, **args)


def _check_modes(modes: Modes, model_set: ModelSet, gain, classifier) -> None:
    """A ValueError where modes per group cannot be: models that couple the groups (per axis, a turn; per channel,
    none of ours), or a gain or classifier (``component_config``'s mappings) that has no ``modes`` (the filter gains
    refuse the range guard with it themselves)."""
    coupled = coupling(model_set, modes.groups)
    if coupled:
        raise ValueError(f"modes per {modes} need motion models that keep the groups apart (F block diagonal per "
                         f"group, a turn's rate with the plane it turns in); {coupled} couple them")
    for role, config in (("gain", gain), ("classifier", classifier)):
        if "modes" not in import_class(config["class_path"], Stage).shared:
            raise ValueError(f"modes per {modes}: the {role} {config['class_path']} has none (filter experts, "
                             "immnet.stages.filtering, and the Bayesian or Transformer mode updates have)")


def _check_taken(settings: dict, stages) -> None:
    """A ValueError where ``p_stay`` or a range guard is set on ``IMMNet`` and none of its ``stages`` takes it (its
    ``Stage.shared``): set, it would change nothing. ``guard=False`` (no guard) is what such a network has."""
    taken = _taken(stage for stage in stages if stage is not None)
    unused = [name for name in ("p_stay", "guard") if name in settings and name not in taken
              and settings[name] is not False]
    if unused:
        raise ValueError(f"IMMNet's {' and '.join(unused)} would change nothing: no component of this network takes "
                         f"{'them' if len(unused) > 1 else 'it'} (filter experts, immnet.stages.filtering, take both; "
                         "the Bayesian mode updates p_stay)")


def _taken(stages) -> set:
    """The settings of ``SET_ONCE`` that some of ``stages`` (stage classes or instances) take (``Stage.shared``)."""
    return {name for stage in stages for name in stage.shared}


def _where(cond: torch.Tensor, a: TensorDict, b: TensorDict) -> TensorDict:
    """Leafwise ``where(cond, a, b)`` with a batch mask ``cond [B]`` broadcast over each leaf (``track_where``)."""
    out = b.empty()
    for key in b.keys(True, True):
        out.set(key, track_where(cond, a.get(key), b.get(key)))
    return out


def _wired(*stages, upstream=()):
    """The stages of a step, each told the keys the stages before it write (``Stage.wire``); ``upstream``: stages
    that run before them."""
    upstream = {unravel_key(k) for s in upstream for k in s.out_keys}
    for stage in stages:
        stage.wire(set(upstream))
        upstream |= {unravel_key(k) for k in stage.out_keys}
    return stages


def _without_step_copies(module, state_dict, prefix, *args) -> None:
    """Drop a state dict's copies of the weights under the steps' indices (``step.module.1.fc1.weight``, as
    checkpoints written before the steps stopped being submodules hold them beside ``gain.fc1.weight``)."""
    for key in [k for k in state_dict if k.startswith((f"{prefix}step.", f"{prefix}expert_step."))]:
        del state_dict[key]


class IMMNet(TensorDictModuleBase):
    """The hybrid tracker. ``model_set``: a YAML path or a list of ``class_path`` entries.

    As a TensorDict module (a policy of ``immnet.data.env.LASTEnv``, TorchRL's recurrent-module
    conventions) one call is one scan: it reads ``measurement`` ``z_t [B, 3]``, its carry (the leaves of
    ``initial_carry``) and ``is_init [B, 1]`` (True: the track restarts from ``initial_carry``), and
    writes ``action`` (``x_{t|t}``) and the next carry under ``"next"``. In an environment, append
    ``make_tensordict_primer()`` (the carry in its specs) and ``torchrl.envs.InitTracker()``::

        env = TransformedEnv(LASTEnv.generate(B, seed), Compose(InitTracker(), net.make_tensordict_primer()))
        rollout = env.rollout(env.base_env.T, net)      # rollout["action"] == net.rollout(z)[0]["state"]
    """

    def __init__(
        self,
        model_set: str | list = "configs/model_sets/imm4.yaml",
        gain: Component | None = None,
        classifier: Component | None = None,
        dt: float = 1.0,
        p_stay: float | None = None,
        guard: bool | dict | None = None,
        interval_range: tuple[float, float] | None = None,
        cov_consistency: float | None = None,
        start_detections: int = 2,
        modes: str = "joint",
        correction: Component | None = None,
    ):
        """``gain``, ``classifier``: the components (``Component``: a ``class_path`` / ``init_args`` mapping);
        ``p_stay``, ``guard``: the Markov chain's staying probability and the range guard, set here once for
        every component that takes them, in place of the components' own values (``None``: as the components
        say). With the IMM interaction the mode update predicts with the transition the
        experts were mixed with (``("mode", "transition")``), so the chain is the interaction's.
        ``interval_range``: the scan intervals ``(lo, hi)`` (s) the network was trained over; None: trained at
        ``dt`` alone (a tracker refuses data at other intervals, ``immnet.tracking.tracker.check_dt``).
        ``cov_consistency``: the weight per scan of the reported covariance's scale, a running mean of the experts'
        normalized innovation squared over 3 (``immnet.stages.fuse``, docs/immnet.md "Covariance consistency");
        None: the fused covariance as it is. It changes what the network reports, not what it estimates.
        ``start_detections``: a track starts from two detections (position, then the differenced velocity: IMMNet's)
        or from one (its position with the gain's start covariance, the step running from the next scan: the linear
        IMMs' start, docs/spec.md section 3; ``immnet.stages.start``).
        ``modes``: one set of mode probabilities for the whole state (``"joint"``, the IMM's) or one per group of
        coordinates (docs/core.md "Modes per group", ``immnet.motion.MODE_GROUPS``): ``"axis"``, each Cartesian axis
        (the decoupled IMM's structure), ``"channel"``, the horizontal plane and the vertical. Each group has its own
        mode probabilities ``("mode", "probs")`` ``[B, G, M]``, its own mix, mode update and fusion, over experts
        whose motion models keep the groups apart (per axis CV and CA; per channel turns too); the gain and the
        classifier are told it (filter experts' likelihoods per group, a classifier's logits per group).
        ``correction``: a learned output correction after the fusion (``immnet.stages.correct.OutputCorrection``, a
        component as ``gain`` is), which the step reports in place of the fused estimate (``estimate``); None: none."""
        super().__init__()
        self.model_set = ModelSet.from_config(model_set)
        self.model_set_config = self.model_set.to_config()
        self.dt = dt
        if interval_range is not None:
            lo, hi = (float(v) for v in interval_range)
            if not (0 < lo <= hi and math.isfinite(hi)):
                raise ValueError(f"interval_range must be (lo, hi) with 0 < lo <= hi, got {interval_range!r}")
            interval_range = (lo, hi)
        self.interval_range = interval_range
        ms = self.model_set
        self.modes = modes = Modes.parse(modes)
        self.groups = modes.groups
        settings = {k: v for k, v in zip(SET_ONCE, (p_stay, guard)) if v is not None} | {"modes": modes}
        gain, classifier = component_config(gain or DEFAULT_GAIN), component_config(classifier or DEFAULT_CLASSIFIER)
        if modes is not Modes.JOINT:
            _check_modes(modes, ms, gain, classifier)
        self.config = spelled({  # plain data: what a checkpoint's hyper_parameters hold to rebuild this network
            "model_set": self.model_set_config["models"], "gain": gain, "classifier": classifier, "dt": dt,
            **{k: v for k, v in settings.items() if k != "modes" or v is not Modes.JOINT}})
        if interval_range is not None:
            self.config["interval_range"] = list(interval_range)
        if cov_consistency is not None:
            self.config["cov_consistency"] = float(cov_consistency)
        if start_detections != 2:
            self.config["start_detections"] = int(start_detections)
        self.start_detections = int(start_detections)
        self.gain = build_component(gain, ms, dt, settings, Gain)
        self.classify = build_component(classifier, ms, dt, settings, ModeUpdate)
        self.interact, self.predict, self.update = self.gain.stages(ms, dt)  # the stages the gain's experts need
        self.fuse = Fuse(ms, consistency=cov_consistency, modes=modes)
        self.correct = None
        if correction is not None:
            correction = component_config(correction)
            self.config["correction"] = spelled(correction)
            self.correct = build_component(correction, ms, dt, settings)
        _check_taken(settings, (self.gain, self.classify, self.correct))
        first = () if self.interact is None else (self.interact,)
        # the step and the experts-alone step run the stages above between a track start's two stages; they are
        # not submodules of their own, so a state dict names each weight once, by the stage's role
        # (``gain.fc1.weight``), whatever the slots
        stages = _wired(*first, self.predict, self.gain, self.update, self.classify, self.fuse)
        # the output correction follows the join: it reads each track's estimate as the step reports it, starts
        # included, and carries its own state (immnet.stages.correct); experts alone have none
        after = () if self.correct is None else _wired(self.correct, upstream=stages)
        alone = (*first, self.predict, self.gain, self.update, self.fuse)
        alone_stages = _wired(*(stage.for_experts_alone() for stage in alone))
        self.start, self.join = self._starts(stages, experts_alone=False, after=after)
        start_alone, join_alone = self._starts(alone_stages, experts_alone=True)
        object.__setattr__(self, "step", TensorDictSequential(self.start, *stages, self.join, *after))
        # the step of tracks that have all started (no start to make): what IMMNet.scan runs then, and what to compile
        # for them (compiled, the whole step computes the starts at every scan: immnet.stages.start)
        object.__setattr__(self, "running_step", TensorDictSequential(*stages, *after))
        object.__setattr__(self, "expert_step", TensorDictSequential(start_alone, *alone_stages, join_alone))
        # the stages built for experts alone (no weights of their own) move with the network (_apply, train)
        object.__setattr__(self, "_alone_only", [m for m in self.expert_step.module if not any(m is s for s in alone)])
        self.register_load_state_dict_pre_hook(_without_step_copies)
        carry = list(self.start.carry_keys)
        self.carry_keys = carry
        self.in_keys = [keys.MEASUREMENT, keys.IS_INIT, *carry, *self.start.inputs]
        self.out_keys = [keys.ACTION, *(("next", *k) for k in carry)]
        self.register_buffer("mode_onehot", torch.nn.functional.one_hot(ms.modes, N_MODES).float())

    def _starts(self, stages, experts_alone: bool, after=()) -> tuple[TrackStart, JoinStarts]:
        """The stages a step begins and ends with: a track's start (``immnet.stages.start``) around ``stages``;
        ``after``: the stages that follow the join, whose carry the start makes too."""
        fuse = stages[-1]
        written = {unravel_key(k) for s in stages for k in s.out_keys}
        start = TrackStart(self.model_set, self.dt, (*stages, *after), experts_alone=experts_alone,
                           detections=self.start_detections)
        fused_cov = keys.FUSED_COV in written and keys.FUSED_COV not in start.carry_keys
        return start, JoinStarts(self.model_set, start, fuse, fused_cov)

    def _apply(self, fn, *args, **kwargs):
        super()._apply(fn, *args, **kwargs)
        for stage in self._alone_only:
            stage._apply(fn, *args, **kwargs)
        return self

    def train(self, mode: bool = True):
        super().train(mode)
        for stage in self._alone_only:
            stage.train(mode)
        return self

    def intervals_for(self, batch: TensorDict) -> torch.Tensor | None:
        """The interval before each scan of ``batch`` ``[B, T]`` (``immnet.data.times.scan_intervals``) in its
        measurements' dtype, or None where every one is this network's ``dt`` (the step then uses its own)."""
        z = batch[keys.MEASUREMENTS]
        intervals = self.own_intervals(scan_intervals(batch, torch.float64, z.device))
        return None if intervals is None else intervals.to(z.dtype)

    def own_intervals(self, intervals: torch.Tensor) -> torch.Tensor | None:
        """``intervals [B, T]`` (s) as this network's step takes them: None where every one after scan 0's is its
        ``dt`` (the step then runs at its own), else as given."""
        return None if bool((intervals[:, 1:] == self.dt).all()) else intervals

    def told_r(self, batch: TensorDict) -> torch.Tensor | None:
        """Each track's measurement std ``r [B]`` of ``batch`` where this network's filter experts are told it
        (``FilterGain(r="data")``: the step's input ``"r"``), else None; a ValueError where the batch has none."""
        if not self.start.told_r:
            return None
        if keys.R not in batch.keys():
            raise ValueError("this IMMNet's filter experts are told each track's measurement std (r='data'); the data "
                             "holds no 'r'")
        return batch[keys.R].to(batch[keys.MEASUREMENTS].dtype).reshape(-1)

    def told_cov(self, batch: TensorDict) -> torch.Tensor | None:
        """Each detection's measurement covariance ``[B, T, 3, 3]`` of ``batch`` (its ``meas_cov``, checked:
        ``immnet.imm.measurement.PerDetection.R``) where this network's filter experts are told it
        (``FilterGain(r="detection")``: the step's input ``"meas_cov"``), else None; a ValueError in one line where the
        batch has none or one is not a covariance."""
        if not self.start.told_cov:
            return None
        if keys.MEAS_COV not in batch.keys():
            raise ValueError("this IMMNet's filter experts are told each detection's measurement covariance "
                             f"(r='detection'); the data holds no {keys.MEAS_COV!r}")
        from immnet.imm.measurement import PerDetection

        z = batch[keys.MEASUREMENTS]
        return PerDetection().R(batch, z.dtype, z.device)

    # the parts a network can learn -> the stage that holds each: the names ``Stage2Module(learn=...)``, ``knock_out``
    # and ``learned_parts`` share (``correction``: the output correction, as ``IMMNet(correction=...)`` names it)
    PARTS = {"gain": "gain", "classifier": "classify", "correction": "correct"}

    def part(self, name: str) -> torch.nn.Module | None:
        """The stage that holds the learned part ``name`` (one of ``PARTS``), None where this network has none (an
        output correction is optional); a ValueError naming the parts for any other name."""
        if name not in self.PARTS:
            raise ValueError(f"no learned part {name!r}; parts: {', '.join(self.PARTS)}")
        return getattr(self, self.PARTS[name], None)

    def learned_parts(self) -> list[str]:
        """The parts of ``PARTS`` this network has with parameters: what it learned or can learn (a model-based
        gain or mode update has none)."""
        return [name for name in self.PARTS
                if (stage := self.part(name)) is not None and any(True for _ in stage.parameters())]

    def knock_out(self, *parts: str) -> "IMMNet":
        """Set the learned correction of ``parts`` to zero, in place, each part its model-based base and the rest of
        the trained network as it is: ``gain``, KalmanNet's noise and gain corrections (and its state correction
        where it has one); ``classifier``, the Transformer's correction of the IMM's mode update; ``correction``, the
        output correction after the fusion (``IMMNet(correction=...)``: the step reports its filters' estimate);
        ``state_correction``, KalmanNet's state correction alone (``KalmanNetFilterGain(state_correction=...)``).
        ``gain`` and ``classifier`` together: IMMNet with nothing learned (the model-based IMM of
        ``tests/test_filtering.py``). What a trained part is worth, without training again. A part with no
        model-based base (the paper's Transformer alone) is refused."""
        for name in parts:
            if name == "state_correction":
                stage = self.gain
                knock_out = stage.knock_out_correction
            elif name in self.PARTS:
                stage = self.part(name)
                if stage is None:
                    what = "output correction" if name == "correction" else name
                    raise ValueError(f"this IMMNet has no {what} to knock out (IMMNet({name}=...))")
                knock_out = stage.knock_out
            else:
                raise ValueError(f"no learned part {name!r}; parts: {', '.join([*self.PARTS, 'state_correction'])}")
            if knock_out is None:
                raise ValueError(f"the {name} {type(stage).__name__} has no model-based base to knock out to")
            knock_out()
        return self

    def interval_columns(self) -> dict[str, int]:
        """The weights that read the interval input (``log(interval / dt)``) and the input column it takes: a
        checkpoint without that input loads into the other columns (``Stage2Module.load_net``)."""
        return self._weights_named(lambda stage: stage.interval_columns())

    def group_rows(self) -> dict[str, int]:
        """The weights whose rows are one block per group of modes (``modes``: a classifier's logits per group) and
        the number of groups: a checkpoint with one joint set of modes loads into each block
        (``Stage2Module.load_net``)."""
        return self._weights_named(lambda stage: stage.group_rows())

    def _weights_named(self, said) -> dict:
        """What ``said(stage)`` of the gain and the classifier says of their weights (stage-level name -> value), under
        every name this network's state dict gives those weights (each under every path that reaches it)."""
        reads = {}  # the parameters themselves
        for stage in (self.gain, self.classify):
            reads.update({id(stage.get_parameter(k)): v for k, v in said(stage).items()})
        return {name: reads[id(p)] for name, p in self.named_parameters(remove_duplicate=False) if id(p) in reads}

    @property
    def n_experts(self) -> int:
        return len(self.model_set)

    @property
    def has_cov(self) -> bool:
        """Whether the step writes a fused covariance ``("fused", "cov")``: its experts carry a covariance (filter
        experts, the analytic gain; ``immnet.stages.fuse``). The paper's KalmanNet experts give a gain only."""
        return keys.FUSED_COV in {unravel_key(k) for k in self.step.out_keys}

    def no_cov_reason(self) -> str:
        """Why this network gives no covariance (for an error message), or '' where it gives one."""
        if self.has_cov:
            return ""
        return (f"this IMMNet's experts carry no covariance: its gain {type(self.gain).__name__} gives each expert a "
                "Kalman gain and nothing else (the paper's KalmanNet experts); filter experts "
                "(immnet.stages.filtering, the recipes') and the analytic gain carry one")

    def estimate(self, carry: TensorDict) -> torch.Tensor:
        """The estimate a scan reports ``[B, 9]``: the output correction's where the network has one
        (``("output", "state")``), else the fused state."""
        return carry.get(keys.FUSED if self.correct is None else keys.OUTPUT)

    def reported_cov(self, carry: TensorDict) -> torch.Tensor:
        """The covariance this network reports for a scan's fused state ``[B, 9, 9]``: the carry's fused covariance,
        times its consistency scale where the network keeps one (``cov_consistency``)."""
        cov = carry.get(keys.FUSED_COV)
        scale = carry.get(keys.COV_SCALE, None)
        return cov if scale is None else cov * scale.to(cov.dtype)[..., None, None]

    def to_mode_probs(self, expert_probs: torch.Tensor) -> torch.Tensor:
        """Expert probabilities ``[..., M]`` summed per data mode ``[..., 4]``; with modes per group
        (``[..., G, M]``) the mean over the Cartesian axes of each axis's group's (a data mode is the whole target's)."""
        probs = expert_probs @ self.mode_onehot.to(expert_probs.dtype)
        return probs if self.groups is None else axis_probs(probs, self.groups).mean(-2)

    def predictive_loglik(self, before: TensorDict, after: TensorDict, reported: bool = False) -> torch.Tensor:
        """The log-likelihood of a scan's measurement under what the network predicted for it, ``[B]``:
        ``log sum_i c^(i) N(nu^(i); 0, S^(i))``, each filter expert's innovation likelihood (``("expert", "loglik")``)
        weighted by the predicted mode probabilities ``c`` (the IMM's Markov prediction ``Pi^T mu_{t-1}`` where the mode
        update has one, else ``mu_{t-1}``); with modes per group, the sum over the groups of each group's. ``before``
        is the carry the scan started from, ``after`` the scan's. 0 where the scan has no detection (the same factor
        for any tracker); NaN where the track had no estimate to predict from (not started before this scan). What a
        bank of networks weighs its members by (``immnet.tracking.bank``); a ValueError for experts that keep no
        likelihood (the paper's KalmanNet experts).

        ``reported``: the prediction of the track as the network *reports* it: each expert's predicted position moved
        by the output correction the network reported at the scan before (``before``'s ``("output", "state")`` less
        its fused estimate; none where ``before`` holds no report, e.g. a track's first scan), ``S`` unchanged
        (``shifted_loglik`` of the filter experts). For a network without an output correction it is the filter's."""
        if keys.EXPERT_LOGLIK not in after.keys(True, True):
            raise ValueError(f"these experts keep no innovation likelihood: {self.no_cov_reason() or 'no filter experts'}")
        shift = self.reported_shift(before) if reported else None
        loglik = after.get(keys.EXPERT_LOGLIK) if shift is None else self.gain.shifted_loglik(after, shift)
        prev = before.get(keys.EXPERT_PROBS)
        prior = self.classify.markov_prior
        log_pred = prior(after, prev) if prior is not None else torch.log(prev.clamp_min(1e-30))
        mixed = torch.logsumexp(log_pred.to(loglik.dtype) + loglik, -1)
        if mixed.dim() > 1:  # modes per group: [B, G]
            mixed = mixed.sum(-1)
        z = after.get(keys.MEASUREMENT)
        mixed = torch.where(torch.isfinite(z).all(-1), mixed, torch.zeros_like(mixed))
        predicted = before.get(keys.AGE) >= self.start_detections
        return torch.where(predicted, mixed, torch.full_like(mixed, float("nan")))

    def reported_shift(self, carry: TensorDict) -> torch.Tensor | None:
        """``[B, 3]`` the position the network reported at the scan of ``carry`` less its fused estimate (the output
        correction; 0 where the track has no estimate), or None where ``carry`` holds no report (no output correction,
        or a carry reduced to ``carry_keys``)."""
        names = carry.keys(True, True)
        if keys.OUTPUT not in names or keys.FUSED not in names:
            return None
        shift = carry.get(keys.OUTPUT)[..., POS_VIEW] - carry.get(keys.FUSED)[..., POS_VIEW]
        return torch.nan_to_num(shift, nan=0.0, posinf=0.0, neginf=0.0)

    # --- the carry ------------------------------------------------------------------------
    def _steps(self, experts_alone: bool):
        return (self.expert_step if experts_alone else self.step).module

    def initial_carry(self, batch: int, experts_alone: bool = False, dtype=torch.float32, device=None) -> TensorDict:
        """A carry of ``batch`` tracks that have not started (age 0): what each stage of the step declares it
        carries (``Stage.carry_spec``, docs/stages.md), the track-start counts ``TrackStart``'s."""
        return self._steps(experts_alone)[0].fresh_carry(batch, dtype, device)

    # --- one scan -------------------------------------------------------------------------
    def scan(self, carry: TensorDict, z: torch.Tensor, experts_alone: bool = False, interval=None, r=None,
             truth: dict | None = None, meas_cov=None) -> TensorDict:
        """Advance every track by one scan of measurements ``z [B, 3]`` (``[B, M, 3]`` experts alone).

        ``interval [B]``: the time since the previous scan per track (s); None: the nominal ``dt``. ``r [B]``: each
        track's measurement std (m), for filter experts told it (``FilterGain(r="data")``); None: none. ``meas_cov [B, 3,
        3]``: each detection's measurement covariance (m^2), for filter experts told it (``FilterGain(r="detection")``;
        any matrix where the scan has no detection); None: none. ``truth``: an
        oracle's inputs of this scan, ``{("truth", name): [B]}`` (``keys.TRUE_MODE``, ``TRUE_TURN_RATE``), for the
        stages that read them (the clairvoyant filters' configuration, ``ClairvoyantKF.network()``). Returns
        the new carry, which also holds this scan's outputs (``("fused", "state")``, ``("expert", "post")``,
        ``("mode", "probs")``, ...). NaN in ``z`` is a missed detection. It is one call of the step (track
        starts included), with the measurement and the interval set; where every track has started, of
        ``running_step`` (the step without the start's two stages, which would change nothing). A track that the filter
        gain's re-acquisition restarts at this scan (``("expert", "reacquire")``, ``immnet.imm.reacquire``) takes the
        step of a fresh carry at this detection: it starts again there, as at its first detection.
        """
        step = self.expert_step if experts_alone else self.step
        if not experts_alone and bool((carry.get(keys.AGE) >= self.start_detections).all()):
            step = self.running_step  # nothing starts: the same result without the start's two stages
        out = step(self._scan_input(carry, z, interval, r, meas_cov, truth))
        restart = out.get(keys.REACQUIRE, None)  # a filter gain with re-acquisition (immnet.imm.reacquire)
        if restart is not None:
            restart = restart & (carry.get(keys.AGE) >= self.start_detections)
            if bool(restart.any()):  # those tracks restart at this detection as at their first
                fresh = self.initial_carry(z.shape[0], dtype=z.dtype, device=z.device)
                out = _where(restart, self.step(self._scan_input(fresh, z, interval, r, meas_cov, truth)), out)
        for key, value in ((keys.INTERVAL, interval), (keys.R, r), (keys.MEAS_COV, meas_cov)):
            if value is not None:
                out.del_(key)
        if truth:
            out.del_(unravel_key(next(iter(truth)))[0])  # the ("truth", ...) inputs
        return out

    @staticmethod
    def _scan_input(carry: TensorDict, z: torch.Tensor, interval, r, meas_cov, truth) -> TensorDict:
        """The step's input of ``scan``: the carry with the scan's measurement and inputs set."""
        td = carry.copy()
        td.set(keys.MEASUREMENT, z)
        for key, value in ((keys.INTERVAL, interval), (keys.R, r)):  # a number or [B]
            if value is not None:
                td.set(key, torch.as_tensor(value, dtype=z.dtype, device=z.device).reshape(-1).expand(z.shape[0]))
        if meas_cov is not None:
            td.set(keys.MEAS_COV, torch.as_tensor(meas_cov, dtype=z.dtype, device=z.device).expand(z.shape[0], 3, 3))
        for key, value in (truth or {}).items():
            td.set(key, value)
        return td

    # --- a policy -------------------------------------------------------------------------
    def make_tensordict_primer(self, dtype=torch.float32):
        """The carry as a ``torchrl.envs.TensorDictPrimer`` (its keys in the environment's specs; zero
        at a reset, where ``is_init`` makes the policy start from ``initial_carry``)."""
        from torchrl.data import Unbounded
        from torchrl.envs import TensorDictPrimer

        carry = self.initial_carry(1, dtype=dtype)
        return TensorDictPrimer(
            {k: Unbounded(shape=carry.get(k).shape[1:], dtype=carry.get(k).dtype) for k in self.carry_keys},
            expand_specs=True,
        )

    def forward(self, td: TensorDict) -> TensorDict:
        """One scan as a TensorDict module (class doc): the carry read from ``td`` (``initial_carry`` where
        ``is_init`` or where ``td`` holds none), ``action`` and ``("next", carry)`` written."""
        z = td.get(keys.MEASUREMENT)
        B = z.shape[0]
        fresh = self.initial_carry(B, dtype=z.dtype, device=z.device)
        present = set(td.keys(True, True))
        missing = [k for k in self.carry_keys if k not in present]
        init = td.get(keys.IS_INIT, None)
        if not missing:
            carry = td.select(*self.carry_keys)
            if init is not None:
                carry = _where(init.reshape(B), fresh, carry)
        elif len(missing) == len(self.carry_keys) and (init is None or bool(init.all())):
            carry = fresh  # the first scan of tracks that all start
        else:
            raise ValueError(f"IMMNet: the TensorDict holds no carry {missing[:3]}{'...' if len(missing) > 3 else ''} for "
                             "tracks that are not starting (is_init False); in an environment, append "
                             "net.make_tensordict_primer()")
        told = (keys.R, keys.MEAS_COV)
        truth = {k: td.get(k) for k in self.start.inputs if k not in told and k in present}  # an oracle's inputs
        new = self.scan(carry, z, interval=td.get(keys.INTERVAL, None), r=td.get(keys.R, None), truth=truth or None,
                        meas_cov=td.get(keys.MEAS_COV, None))
        td.set(keys.ACTION, self.estimate(new))
        for key in self.carry_keys:
            td.set(("next", *key), new.get(key))
        return td

    # --- a whole sequence -----------------------------------------------------------------
    def rollout(self, measurements: torch.Tensor, carry: TensorDict | None = None, experts_alone: bool = False,
                intervals: torch.Tensor | None = None, return_cov: bool = False, r: torch.Tensor | None = None,
                truth: dict | None = None, return_loglik: bool | str = False, meas_cov: torch.Tensor | None = None):
        """Run over ``measurements [B, T, 3]`` (``[B, M, T, 3]`` experts alone), with the interval before each
        scan ``intervals [B, T]`` (``immnet.data.times.scan_intervals``; None: the nominal ``dt`` at every scan)
        and, for filter experts told it (``r="data"``), each track's measurement std ``r [B]``, or (``r="detection"``)
        each detection's covariance ``meas_cov [B, T, 3, 3]`` (``told_cov``); ``truth``: an
        oracle's inputs over the sequence, ``{("truth", name): [B, T]}`` (``scan``'s, each scan's column).

        Returns ``(outputs, carry)``: ``outputs`` a TensorDict ``[B, T]`` with ``state``
        (``[B, T, 9]``, or ``[B, T, M, 9]`` experts alone), ``expert_probs`` and ``mode_logits``
        ``[B, T, M]`` and ``expert_post [B, T, M, 9]`` (not experts alone), and with ``return_cov`` the fused
        covariance ``state_cov [B, T, 9, 9]`` (``[B, T, M, 9, 9]`` experts alone; a ValueError saying why where
        the experts carry none, ``has_cov``), and with ``return_loglik`` each scan's ``loglik [B, T]``
        (``predictive_loglik``; True or ``"filter"``: of the filter's prediction, ``"reported"``: of the track as
        reported, ``Likelihood``; ``loglik_asked``); ``carry`` continues the rollout
        (truncated BPTT detaches it between chunks).
        """
        B, T = measurements.shape[0], measurements.shape[-2]
        loglik = loglik_asked(return_loglik)
        if return_cov:
            fuse = next(m for m in self._steps(experts_alone) if isinstance(m, Fuse))
            if fuse.cov is None:
                raise ValueError(self.no_cov_reason() or "these experts carry no covariance")
        if carry is None:
            carry = self.initial_carry(B, experts_alone, measurements.dtype, measurements.device)
        per_scan = {} if experts_alone else {keys.ROLLOUT_EXPERT_PROBS: keys.EXPERT_PROBS,
                                             keys.ROLLOUT_MODE_LOGITS: keys.MODE_LOGITS,
                                             keys.ROLLOUT_EXPERT_POST: keys.EXPERT_POST}
        states, covs, logliks, seqs = [], [], [], {k: [] for k in per_scan}
        for t in range(T):
            before = carry
            carry = self.scan(carry, measurements[..., t, :], experts_alone,
                              None if intervals is None else intervals[:, t], r,
                              None if truth is None else {k: v[:, t] for k, v in truth.items()},
                              None if meas_cov is None else meas_cov[:, t])
            states.append(carry.get(keys.FUSED) if experts_alone else self.estimate(carry))
            if return_cov:
                covs.append(self.reported_cov(carry))
            if loglik is not None and not experts_alone:
                logliks.append(self.predictive_loglik(before, carry, reported=loglik is Likelihood.REPORTED))
            for name, key in per_scan.items():
                seqs[name].append(carry.get(key))
        out = {keys.STATE: torch.stack(states, 1), **{name: torch.stack(seq, 1) for name, seq in seqs.items()}}
        if return_cov:
            out[keys.STATE_COV] = torch.stack(covs, 1)
        if logliks:
            out[keys.LOGLIK] = torch.stack(logliks, 1)
        return TensorDict(out, batch_size=[B, T]), carry
