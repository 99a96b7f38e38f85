"""IMMNet and plain KalmanNet as methods of ``immnet evaluate`` (the ``name / needs / track`` protocol)."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict

from immnet import keys
from immnet.data.times import nominal_dt, scan_intervals
from immnet.data.validate import gate_measurements
from immnet.filters.base import before_first_detection, blank_before_first_detection
from immnet.tracking.tracker import AS_CONFIGURED, PRETRAINED, Tracker, check_dt, load_network


class _LearnedMethod:
    """What the learned methods share: ``net`` (an ``IMMNet``), ``name``, and the ``dt`` check."""

    needs: tuple[str, ...] = ()
    net = None

    def _returns_cov(self, return_cov: bool) -> None:
        """``return_cov`` kept; a ValueError naming why where the network's experts carry no covariance."""
        if return_cov and not self.net.has_cov:
            raise ValueError(f"{self.name}: {self.net.no_cov_reason()}")
        self.return_cov = return_cov

    def check(self, batch: TensorDict) -> None:
        """A ValueError when the data's ``dt`` is not the one the network was trained at (:func:`check_dt`)."""
        if keys.DT in batch.keys() or keys.TIME in batch.keys():
            intervals = scan_intervals(batch)
            check_dt(self.net, intervals if intervals.shape[-1] else nominal_dt(batch), self.name)


class IMMNetMethod(_LearnedMethod):
    """A trained IMMNet (``checkpoint``: a Lightning checkpoint; default: the shipped weights); ``guard``
    its range guard as ``load_network``'s (``"checkpoint"``: as trained; ``immnet evaluate --guard``), ``adapt``
    its filter experts' adaptive process noise as ``load_network``'s, ``r`` their measurement std as
    ``load_network``'s (``"data"``: each track's from the data, as the model-based filters are told it); ``knock_out``
    learned parts set to their model-based base (``IMMNet.knock_out``: ``gain``, ``classifier``), the ablations of a trained network;
    ``reacquire`` its filter experts' re-acquisition as ``load_network``'s.

    Its estimates are ``Tracker.track``'s: NaN before a track's first detection. ``immnet evaluate`` scores a data
    set's window as one track, so its tracker has no coasting limit (``max_coast=math.inf``: a track coasts through
    any stretch without detections; the limit is the streaming and CSV APIs', ``Tracker(max_coast=...)``). ``return_cov``: also the fused
    covariance ``state_cov [B, T, 9, 9]`` (``IMMNet.rollout``'s); a ValueError now, naming why, for a checkpoint
    whose experts carry none (the paper's KalmanNet experts)."""

    build_options = {"checkpoint": None, "r": "checkpoint", "return_cov": False, "guard": "checkpoint"}

    def __init__(self, checkpoint: str | None = None, name: str = "immnet", batch_size: int = 500, guard=AS_CONFIGURED,
                 adapt=AS_CONFIGURED, return_cov: bool = False, knock_out: list[str] | tuple[str, ...] = (), r=AS_CONFIGURED,
                 reacquire=AS_CONFIGURED):
        tracker = Tracker(load_network(checkpoint or PRETRAINED, guard, adapt, r, reacquire).knock_out(*knock_out),
                          max_coast=math.inf)
        self._use(tracker, name, batch_size, return_cov)

    def _use(self, tracker: Tracker, name: str, batch_size: int, return_cov: bool) -> None:
        self.name, self.tracker, self.net, self.batch_size = name, tracker, tracker.net, batch_size
        start = self.net.start  # its filter experts read what they are told: each track's r, each detection's R
        self.needs = ((keys.R,) if start.told_r else ()) + ((keys.MEAS_COV,) if start.told_cov else ())
        self._returns_cov(return_cov)

    @classmethod
    def from_tracker(cls, tracker: Tracker, name: str = "immnet", batch_size: int = 500, return_cov: bool = False):
        """The method of a loaded ``Tracker`` (its network as loaded: guard, adaptation, gate, coasting limit)."""
        self = cls.__new__(cls)
        self._use(tracker, name, batch_size, return_cov)
        return self

    def track(self, batch: TensorDict) -> TensorDict:
        self.check(batch)  # every interval the one it was trained at, or inside its interval_range
        out = self.tracker.track(batch[keys.MEASUREMENTS], self.batch_size, self.net.intervals_for(batch),
                                 return_cov=self.return_cov, r=self.net.told_r(batch),
                                 meas_cov=self.net.told_cov(batch))
        names = (keys.STATE, keys.MODE_PROBS, keys.STATE_COV) if self.return_cov else (keys.STATE, keys.MODE_PROBS)
        return TensorDict({k: out[k].double() for k in names}, batch_size=batch.batch_size)


class KalmanNetMethod(_LearnedMethod):
    """Plain KalmanNet: one trained expert running alone (its own posterior is its estimate).

    ``expert`` names the expert of the checkpoint's model set (e.g. ``"ca"``); a checkpoint of the
    single-expert ablation has one. Measurements a sensor cannot report are missed detections
    (``immnet.data.validate.gate_measurements``); the estimate is NaN before a track's first detection.
    ``return_cov``: also the expert's own covariance ``state_cov [B, T, 9, 9]`` (a filter expert's; a ValueError
    naming why for the paper's KalmanNet experts, which carry none).
    """

    build_options = {"checkpoint": None, "return_cov": False}

    def __init__(self, checkpoint: str | None = None, expert: str | None = None, name: str = "kalmannet", batch_size: int = 500,
                 return_cov: bool = False):
        self.name = name
        self.net = load_network(checkpoint or PRETRAINED)
        self._returns_cov(return_cov)
        names = self.net.model_set.names
        if expert is None and len(names) > 1:
            raise ValueError(f"kalmannet needs `expert` naming one of {names} for a checkpoint with several experts")
        if expert is not None and expert not in names:
            raise ValueError(f"expert {expert!r} is not in this checkpoint's model set {names}")
        self.index = names.index(expert) if expert is not None else 0
        self.batch_size = batch_size

    @torch.no_grad()
    def track(self, batch: TensorDict) -> TensorDict:
        self.check(batch)
        z, _ = gate_measurements(batch[keys.MEASUREMENTS].float())
        intervals = self.net.intervals_for(batch)  # None where every one is the network's dt
        M, states, covs = self.net.n_experts, [], []
        for i in range(0, z.shape[0], self.batch_size):
            zi = z[i : i + self.batch_size].unsqueeze(1).expand(-1, M, -1, -1)
            gaps = None if intervals is None else intervals[i : i + self.batch_size].to(z.dtype)
            out, _ = self.net.rollout(zi, experts_alone=True, intervals=gaps, return_cov=self.return_cov)
            states.append(out[keys.STATE][:, :, self.index])
            if self.return_cov:
                covs.append(out[keys.STATE_COV][:, :, self.index])
        waiting = before_first_detection(z)
        out = {keys.STATE: blank_before_first_detection(torch.cat(states).double(), waiting)}
        if self.return_cov:
            out[keys.STATE_COV] = blank_before_first_detection(torch.cat(covs).double(), waiting)
        return TensorDict(out, batch_size=batch.batch_size)
