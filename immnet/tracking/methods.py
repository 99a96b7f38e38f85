"""IMMNet and plain KalmanNet as methods of ``immnet evaluate`` (the ``name / needs / track`` protocol)."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from immnet import keys
from immnet.data.times import nominal_dt, scan_intervals
from immnet.data.validate import gate_measurements
from immnet.filters.base import before_first_detection, blank_before_first_detection
from immnet.tracking.tracker import KEEP, PRETRAINED, Tracker, load_network


def check_dt(net, dt, name: str = "immnet", method=None) -> None:
    """A ValueError unless every sampling interval in ``dt`` is one the network was trained at.

    A method that takes any interval (``any_interval``: the model-based filters, which build ``F(dt)``
    and ``Q(dt)`` per scan) is never refused. A learned tracker is tied to its training intervals: a
    network trained over a range (``net.interval_range = (lo, hi)``) takes any interval in it; one
    trained at one interval (``interval_range`` absent or None) only ``net.dt``: on other data it
    would run as if each step lasted ``net.dt`` (a velocity of ``(z_1 - z_0) / net.dt``, turn rates and
    accelerations per step), off by ``dt / net.dt`` without any sign of it.
    """
    if getattr(method, "any_interval", False) or getattr(net, "any_interval", False):
        return
    values = torch.unique(torch.as_tensor(dt, dtype=torch.float64).reshape(-1))
    values = values[~torch.isnan(values)]
    span = getattr(net, "interval_range", None)
    others = "the model-based methods take any interval (e.g. --method imm-tuned)"
    if span is not None:
        lo, hi = float(span[0]), float(span[1])
        tol = 1e-6 * max(1.0, hi)
        bad = [float(v) for v in values if not lo - tol <= float(v) <= hi + tol]
        if bad:
            raise ValueError(
                f"{name} was trained on intervals {lo:g}-{hi:g} s but this data has an interval of "
                f"{', '.join(f'{v:g}' for v in bad[:5])}{', ...' if len(bad) > 5 else ''} s, outside that range; "
                f"resample the data, train a model over this range (DataSpec dt), or use a method that "
                f"takes any interval ({others})")
        return
    bad = [float(v) for v in values if abs(float(v) - net.dt) > 1e-6 * max(1.0, net.dt)]
    if bad:
        raise ValueError(
            f"{name} was trained on data sampled at dt = {net.dt:g} s but this data has dt = "
            f"{', '.join(f'{v:g}' for v in bad[:5])}{', ...' if len(bad) > 5 else ''} s; it was trained at that one "
            f"interval only, and a learned tracker only knows its training interval (its velocities would be off "
            f"by the ratio): resample the data to dt = {net.dt:g} s, train a model at this dt (DataSpec dt), or use a "
            f"method that takes any "
            f"interval ({others})")


class _LearnedMethod:
    """What the learned methods share: ``net`` (an ``IMMNet``), ``name``, and the ``dt`` check."""

    needs: tuple[str, ...] = ()
    net = None

    def check(self, batch: TensorDict) -> None:
        """A ValueError when the data's ``dt`` is not the one the network was trained at (:func:`check_dt`)."""
        if keys.DT in batch.keys() or keys.TIME in batch.keys():
            intervals = scan_intervals(batch)
            check_dt(self.net, intervals if intervals.shape[-1] else nominal_dt(batch), self.name)


class IMMNetMethod(_LearnedMethod):
    """A trained IMMNet (``checkpoint``: a Lightning checkpoint; default: the shipped weights); ``guard``
    its range guard as ``load_network``'s (``"checkpoint"``: as trained; ``immnet evaluate --guard``), ``adapt``
    its filter experts' adaptive process noise as ``load_network``'s.

    Its estimates are ``Tracker.track``'s: NaN before a track's first detection."""

    def __init__(self, checkpoint: str | None = None, name: str = "immnet", batch_size: int = 500, guard=KEEP,
                 adapt=KEEP):
        self.name = name
        self.tracker = Tracker(load_network(checkpoint or PRETRAINED, guard, adapt))
        self.net = self.tracker.net
        self.batch_size = batch_size

    def track(self, batch: TensorDict) -> TensorDict:
        self.check(batch)  # every interval the one it was trained at, or inside its interval_range
        out = self.tracker.track(batch[keys.MEASUREMENTS], self.batch_size, self.net.intervals_for(batch))
        return TensorDict(
            {keys.STATE: out[keys.STATE].double(), keys.MODE_PROBS: out[keys.MODE_PROBS].double()},
            batch_size=batch.batch_size,
        )


class KalmanNetMethod(_LearnedMethod):
    """Plain KalmanNet: one trained expert running alone (its own posterior is its estimate).

    ``expert`` names the expert of the checkpoint's model set (e.g. ``"ca"``); a checkpoint of the
    single-expert ablation has one. Measurements a sensor cannot report are missed detections
    (``immnet.data.validate.gate_measurements``); the estimate is NaN before a track's first detection.
    """

    def __init__(self, checkpoint: str | None = None, expert: str | None = None, name: str = "kalmannet", batch_size: int = 500):
        self.name = name
        self.net = load_network(checkpoint or PRETRAINED)
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
        M, states = self.net.n_experts, []
        for i in range(0, z.shape[0], self.batch_size):
            zi = z[i : i + self.batch_size].unsqueeze(1).expand(-1, M, -1, -1)
            out, _ = self.net.rollout(zi, experts_alone=True)
            states.append(out[keys.STATE][:, :, self.index])
        state = blank_before_first_detection(torch.cat(states).double(), before_first_detection(z))
        return TensorDict({keys.STATE: state}, batch_size=batch.batch_size)
