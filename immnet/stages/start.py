"""Track starts as stages of the step: ``TrackStart`` first, ``JoinStarts`` last.

A track starts from two detections (docs/stages.md, "Track start and missed detections"): at its first the estimate is
``[z_0, 0, 0]``, at its second ``[z_1, (z_1 - z_0) / elapsed, 0]`` (position and differenced velocity,
``elapsed`` the time since the first detection, missed scans between counting), and from its third scan on
the step's estimate is the track's. Tracks start independently (the carry holds each one's ``age``), so
one step serves a batch of tracks at any point of their lives and the streaming ``Tracker``:

* ``TrackStart`` (first in the step) reads the carry as the previous scan left it and the measurement,
  and writes ``("start", "tracks")`` (the tracks with ``age < 2``) and ``("start", "carry")``: what each
  of them carries after this scan. A first detection gives the carry a track that has not started holds
  (each stage's ``carry_spec``) with what each stage sets at a start (``Stage.start_carry``), a second the
  same from the differenced velocity; a track that misses before its second detection keeps its carry,
  one more scan (and its interval) elapsed since its first. It carries the track-start counts itself
  (``("memory", "age")``, ``("memory", "start_scans")``, ``("memory", "start_time")``).
* the stages of the step run for every track (a starting track's results are not used);
* ``JoinStarts`` (last) takes the start carry where a track starts and the step's elsewhere: a starting
  track's modes the classifier's at a start (uniform; an oracle's the truth's), each expert's estimate the start estimate, its fused covariance the one of its
  start covariances (where the step fuses one and does not carry it). It consumes the ``("start", ...)``
  keys (removes them), so the carry holds only what the stages declare they carry.

Where no track starts (every one has run two scans) ``TrackStart`` writes ``("start", "tracks")`` alone, all
False, and ``JoinStarts`` leaves the step's results as they are: one check a scan, in eager mode; compiled
(``torch.compile``), the two stages compute the starts at every scan, so the step traces as one graph. That
costs a compiled step of tracks that have all started about as much again as the filters' own work
(BENCHMARKS.md): ``IMMNet.running_step``, the step without the two, is what to compile for them, and
``IMMNet.scan`` runs it wherever no track starts.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict
from tensordict.utils import unravel_key

from immnet import keys
from immnet.motion import POS, VEL, ModelSet
from immnet.stages.base import Stage, measured, per_expert, step_input, track_where

STEP_INPUTS = (keys.R, keys.MEAS_COV, keys.TRUE_MODE, keys.TRUE_TURN_RATE, keys.TRUE_RESTART)
"""The step's inputs per track that are neither carried nor measured: each track's measurement std or each detection's
covariance ``[B, 3, 3]`` (a filter gain told it, ``r="data"``, ``r="detection"``) and an oracle's truth (the clairvoyant filters, docs/stages.md); ``IMMNet.scan`` sets them."""


class TrackStart(Stage):
    """The first stage of a step: what each starting track carries after this scan (module doc)."""

    out_keys = [keys.STARTING, keys.START_CARRY]

    def __init__(self, model_set: ModelSet, dt: float, stages, experts_alone: bool = False, detections: int = 2):
        """``stages``: the stages of the step after this one, whose ``carry_spec`` and ``start_carry`` make the
        carry (held, not registered: their weights are the network's); ``experts_alone``: the step of stage 1;
        ``detections``: how many detections a start takes, 2 (the module doc's) or 1 (the first detection alone,
        the step running from the next scan: the linear IMMs' start, docs/spec.md section 3)."""
        super().__init__(model_set)
        if detections not in (1, 2):
            raise ValueError(f"a track starts from 1 or 2 detections, got {detections!r}")
        self.dt = dt
        self.experts_alone = experts_alone
        self.detections = int(detections)
        object.__setattr__(self, "_stages", tuple(stages))
        self.carry_keys = [unravel_key(k) for k in self.fresh_carry(1).keys(True, True)]  # the carry's leaves
        self.carried = [unravel_key(k) for stage in (self, *stages) for k in stage.carry_spec(1, experts_alone)]
        # the step's inputs beside the measurement and the interval that a stage reads (each track's measurement std
        # where a filter gain is told it, r 'data'; an oracle's truth): a start reads them too
        read = {unravel_key(k) for stage in stages for k in stage.in_keys}
        self.inputs = [k for k in STEP_INPUTS if k in read]
        self.told_r = keys.R in self.inputs
        self.told_cov = keys.MEAS_COV in self.inputs
        self.in_keys = [keys.MEASUREMENT, *self.carried, *self.inputs]  # a nested key whole

    def carry_spec(self, batch: int, experts_alone: bool = False, dtype=torch.float32, device=None) -> dict:
        """The track-start counts, zero before a track's first detection."""
        return {
            keys.AGE: torch.zeros(batch, dtype=torch.long, device=device),
            keys.START_SCANS: torch.zeros(batch, dtype=torch.long, device=device),
            keys.START_TIME: torch.zeros(batch, dtype=dtype, device=device),
        }

    def fresh_carry(self, batch: int, dtype=torch.float32, device=None) -> TensorDict:
        """The carry of ``batch`` tracks that have not started: what this stage and each stage after it declare
        they carry (``Stage.carry_spec``); a key declared by two stages is a ValueError."""
        td = TensorDict({}, batch_size=[batch], device=device)
        owner = {}
        for stage in (self, *self._stages):
            for key, value in stage.carry_spec(batch, self.experts_alone, dtype, device).items():
                key = unravel_key(key)
                if key in owner:
                    raise ValueError(f"{type(stage).__name__} and {owner[key]} both carry {key}")
                owner[key] = type(stage).__name__
                td.set(key, value)
        return td

    def _started(self, carry: TensorDict, z: torch.Tensor, second: bool, interval) -> TensorDict:
        """The carry after a track's first (``second=False``) or second detection ``z``, from the ``carry`` before
        it: the start estimate and what each stage sets at a start (``Stage.start_carry``, which reads the time
        since the first detection as the carry's ``START_TIME``); the rest as before a start."""
        fresh = self.fresh_carry(z.shape[0], z.dtype, z.device)
        x = torch.zeros(z.shape[:-1] + (9,), dtype=z.dtype, device=z.device)
        x[..., list(POS)] = z
        if second:
            # differenced velocity over the time since the first detection (missed scans between count)
            if interval is None:
                elapsed = (carry.get(keys.START_SCANS).clamp_min(1) * self.dt).to(z.dtype)
            else:
                elapsed = (carry.get(keys.START_TIME) + interval).to(z.dtype)
            x[..., list(VEL)] = (z - carry.get(keys.PREV_MEASUREMENT)) / elapsed.view(-1, *([1] * (z.dim() - 1)))
            carry = carry.clone(False)
            carry.set(keys.START_TIME, elapsed)
        else:
            fresh.set(keys.START_SCANS, torch.ones_like(carry.get(keys.AGE)))
        for stage in self._stages:
            x = stage.start_estimate(carry, z, x, second)
        for stage in self._stages:
            for key, value in stage.start_carry(carry, z, x, second).items():
                fresh.set(key, value)
        fresh.set(keys.AGE, carry.get(keys.AGE) + 1)
        return fresh

    def forward(self, td):
        age = td.get(keys.AGE)
        starting = age < self.detections
        td.set(keys.STARTING, starting)
        if not torch.compiler.is_compiling() and not bool(starting.any()):  # every track running: nothing starts
            return td
        z = td.get(keys.MEASUREMENT)
        interval = td.get(keys.INTERVAL, None)
        carry = td.select(*self.carry_keys)
        has = measured(z).reshape(z.shape[0], -1).all(-1)
        for key in self.inputs:  # what a start reads beside the carry: the told measurement std, the truth
            carry.set(key, step_input(td, key))
        first = self._started(carry, z, second=False, interval=interval)
        second = self._started(carry, z, second=True, interval=interval) if self.detections == 2 else None
        start = carry.empty()
        for key in self.carry_keys:
            # a detection: the first or the second; none: the carry as it was
            value = carry.get(key) if second is None else track_where(has & (age == 1), second.get(key), carry.get(key))
            start.set(key, track_where(has & (age == 0), first.get(key), value))
        if self.detections == 2:  # a started track that missed its second detection: one more scan elapses
            waiting = (age == 1) & ~has
            for key, elapsed in ((keys.START_SCANS, 1), (keys.START_TIME, self.dt if interval is None else interval)):
                start.set(key, torch.where(waiting, carry.get(key) + elapsed, start.get(key)))
        td.set(keys.START_CARRY, start)
        return td


class JoinStarts(Stage):
    """The last stage of a step: the start carry where a track starts, the step's results elsewhere (module doc)."""

    def __init__(self, model_set: ModelSet, start: TrackStart, fuse, fused_cov: bool):
        """``start``: the step's ``TrackStart`` (its carry's keys); ``fuse``: the step's ``Fuse`` (held, not
        registered), whose covariance a starting track's fused covariance is, where ``fused_cov`` (the step fuses
        a covariance and does not carry it)."""
        super().__init__(model_set)
        self.carry_keys = list(start.carry_keys)  # the leaves
        object.__setattr__(self, "_fuse", fuse)
        self.fused_cov = fused_cov
        reads = [keys.STARTING, keys.START_CARRY, *start.carried, keys.FUSED, keys.EXPERT_POST]
        writes = [*start.carried, keys.EXPERT_POST]
        if fused_cov:
            reads += [fuse.cov, keys.FUSED_COV]
            writes += [keys.FUSED_COV]
        self.in_keys = list(dict.fromkeys(unravel_key(k) for k in reads))
        self.out_keys = list(dict.fromkeys(unravel_key(k) for k in writes))

    def forward(self, td):
        starting = td.pop(keys.STARTING)
        start = td.pop(keys.START_CARRY, None)
        parent = unravel_key(keys.STARTING[:-1])  # ("start", ...): emptied, it goes too
        if parent in td.keys() and not list(td.get(parent).keys()):
            td.del_(parent)
        if start is None:  # nothing starts (TrackStart wrote no start carry)
            return td
        for key in self.carry_keys:
            td.set(key, track_where(starting, start.get(key), td.get(key)))
        # a starting track has no expert estimates of its own yet: each expert's is the start estimate
        # (the step ran on its carry before the start, so its posteriors there mean nothing)
        fused = td.get(keys.FUSED)
        post = td.get(keys.EXPERT_POST)
        td.set(keys.EXPERT_POST, track_where(starting, per_expert(fused, post.shape[1]), post))
        if self.fused_cov:  # fused from the experts' start covariances, not carried
            td.set(keys.FUSED_COV, track_where(starting, self._fuse.covariance(td, fused), td.get(keys.FUSED_COV)))
        return td
