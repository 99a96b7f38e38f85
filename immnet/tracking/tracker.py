"""Run a trained IMMNet online: one scan at a time, many tracks at once.

    tracker = Tracker.pretrained("general")   # or Tracker.from_checkpoint("runs/.../best.ckpt")
    tracker.reset(n_tracks=3)
    out = tracker.step(z)                     # z [3, 3]; NaN row = missed detection
    out["fused", "state"], out["expert", "post"], out["mode", "probs"], out["mode_probs"]

Tracks start and end independently: ``step(z, reset=mask)`` restarts the tracks in ``mask`` (a new
target on that slot); a track starts from its first two measurements (see ``immnet.stages.network``).
``step`` over a sequence gives the same numbers as the batched ``track``.

No made-up output: until a track's first detection every output of it (state, expert posteriors,
mode probabilities) is NaN, and a track with no detection at all is NaN throughout; the carry stays
finite. A measurement a sensor cannot report (a non-finite component, or ``|z_a| > max_position``,
default 1e7 m: ``immnet.data.validate.gate_measurements``) is a missed detection; ``tracker.n_gated``
counts them: in the last ``track`` call, or over the ``step`` calls since the last ``reset``.

The recipes' models carry a range guard (``immnet.imm.guard``): 3D-LAST's surveillance region,
where a target turns back beyond 33 km and within 4 km of the radar, and its speed envelope, where a
CA maneuver leaving 40-330 m/s turns for one scan. For data from another region, load with
``guard=None`` (no guard) or ``guard={"outer": ..., "inner": ...}`` (``immnet track --guard``; add
``"speeds": False`` to drop the speed rules, or ``speed_min``/``speed_max``/``vz_max`` to move them).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from immnet import keys
from immnet.checkpoints import BANK, DEFAULT_WEIGHTS, PRETRAINED, shipped  # PRETRAINED: re-exported here too
from immnet.data.validate import MAX_ABS_POSITION, check_limit
from immnet.filters.base import blank_before_first_detection
from immnet.stages import IMMNet
from immnet.tracking.bank import NetworkBank
from immnet.tracking.segments import MAX_COAST, check_coast
from immnet.tracking.networks import (  # noqa: F401  (re-exported: where the trackers' users import them from)
    AS_CONFIGURED, as_measurements, begin_scan, by_segments, check_dt, check_n_tracks, check_scan, coast_scan,
    fresh_tracks, guarded, load_network, next_origin, on_cpu, outputs_to_world, per_track, provenance_of,
    read_checkpoint, run_network, scans_served, select_rows, to_local,
)


def check_meas_cov(R, z: torch.Tensor) -> torch.Tensor:
    """``R`` as float64 ``[B, 3, 3]`` for a scan ``z [B, 3]``; a ValueError unless it has that shape and, where the track
    has a detection, is finite, symmetric and positive definite (m^2)."""
    cov = torch.as_tensor(np.asarray(R) if not isinstance(R, torch.Tensor) else R).to(torch.float64)
    want = (z.shape[0], 3, 3)
    if tuple(cov.shape) != want:
        raise ValueError(f"R is each track's measurement covariance [n_tracks, 3, 3] = {list(want)}, got "
                         f"{list(cov.shape)}")
    seen = ~torch.isnan(z).all(-1)
    ok = torch.isfinite(cov).all(-1).all(-1) & torch.isclose(cov, cov.transpose(-1, -2), rtol=1e-9, atol=0).all(-1).all(-1)
    ok = ok & (torch.linalg.cholesky_ex(torch.where(ok[:, None, None], cov, torch.eye(3, dtype=cov.dtype)))[1] == 0)
    bad = (seen & ~ok).nonzero()
    if len(bad):
        i = int(bad[0])
        raise ValueError(f"R of track {i} is not a symmetric positive-definite covariance (m^2): "
                         f"{cov[i].tolist()}")
    return cov


class Tracker:
    """A stateful wrapper around ``IMMNet.scan`` for streaming use (inference only).

    ``max_position``: the largest ``|z_a|`` (m) a detection may have; beyond it, or non-finite, a
    measurement is a missed detection, counted in ``n_gated`` (module doc). ``max_coast``: the seconds a track may go
    without a detection before it restarts (``step``; ``immnet.tracking.segments.MAX_COAST``, ``inf``: never).
    ``name``, ``path``: what ``repr`` names, the shipped name or the checkpoint it was loaded from (None: neither).
    """

    def __init__(self, net: IMMNet, max_position: float = MAX_ABS_POSITION, max_coast: float = MAX_COAST,
                 name: str | None = None, path: str | Path | None = None):
        self.net = on_cpu(net, "a Tracker").eval()
        self._guarded = guarded(self.net)  # read at every scan
        self.max_position = check_limit(max_position)
        self.max_coast = check_coast(max_coast, float(self.net.dt))
        self.carry: TensorDict | None = None
        self.fresh: torch.Tensor | None = None  # [B] no scan yet since a reset: the first one's interval is nominal
        self.since: torch.Tensor | None = None  # [B] s since each track's last detection (or its start): max_coast's
        self.last: torch.Tensor | None = None  # [B] the interval each track's last scan was taken at (NaN: none yet)
        self.origin: torch.Tensor | None = None  # [B, 3] float64: each track's frame, its first detection (NaN: none)
        self.n_gated = 0
        self.name, self.path = name, None if path is None else Path(path)

    def __repr__(self) -> str:
        """What the tracker is: its network, the scan intervals it serves, its range guard and its provenance."""
        name = self.name or (str(self.path) if self.path is not None else type(self.net).__name__)
        guard = "range guard" if guarded(self.net) else "no range guard"
        return f"Tracker({name}: scans of {scans_served(self.net)}, {guard}; {provenance_of(self.path)})"

    @classmethod
    def from_checkpoint(cls, path: str | Path, guard=AS_CONFIGURED, adapt=AS_CONFIGURED, max_position: float = MAX_ABS_POSITION,
                        r=AS_CONFIGURED, robust=AS_CONFIGURED) -> "Tracker":
        """The IMMNet of a checkpoint; ``guard``, ``adapt``, ``r`` and ``robust`` as in ``load_network``;
        ``max_position`` the gate on measurements (``immnet.data.validate``)."""
        return cls(load_network(path, guard, adapt, r, robust=robust), max_position, path=path)

    @classmethod
    def pretrained(cls, name: str = DEFAULT_WEIGHTS, guard=AS_CONFIGURED, adapt=AS_CONFIGURED, max_position: float = MAX_ABS_POSITION,
                   r=AS_CONFIGURED, robust=AS_CONFIGURED):
        """Weights shipped inside the package by name (``immnet.checkpoints.SHIPPED``, provenance in
        ``immnet/pretrained/PROVENANCE-*.md``): ``general`` (any scan interval from 0.5 to 12 s, real flights and
        3D-LAST, no range guard), ``3dlast`` (the 3D-LAST benchmark network, 1 s, with 3D-LAST's range guard:
        ``guard=None`` for data from another surveillance region), ``real`` (1 s real flights), ``real-5s`` (real
        flights at a surveillance radar's 4.5-5.5 s scans), ``real-11s`` (at an en-route radar's 10-12 s scans),
        ``real-4.5-12s`` (real flights at any interval from 4.5 to 12 s).
        ``adapt=True`` adds adaptive process noise (targets noisier than the training data's; docs/immnet.md).
        ``r``: the radar's measurement std in metres where it is known (each shipped network estimates each track's
        from its measurements; ``load_network``). ``robust``: Huber's ``k`` of the filter experts' update (plots with
        outliers; ``load_network``). ``bank``, the default: all six as one tracker, each weighed per
        track by how well it predicts the track (``immnet.tracking.bank.NetworkBank``: ``reset``, ``step`` and
        ``track`` as here, its ``member_probs`` in place of one network's expert outputs; no range guard unless
        ``guard`` asks)."""
        if name == BANK:
            return NetworkBank.from_names(guard=None if isinstance(guard, str) and guard == AS_CONFIGURED else guard, adapt=adapt,
                                          r=r, max_position=max_position, robust=robust)
        tracker = cls.from_checkpoint(shipped(name), guard, adapt, max_position, r, robust)
        tracker.name = name
        return tracker

    def reset(self, n_tracks: int) -> None:
        """``n_tracks`` (a whole number, at least 1) tracks that have not started; ``n_gated`` back to 0."""
        n_tracks = check_n_tracks(n_tracks)
        self.carry = self.net.initial_carry(n_tracks)
        fresh_tracks(self, n_tracks)

    @torch.no_grad()
    def step(self, z: torch.Tensor, reset: torch.Tensor | None = None, dt=None, r=None, R=None) -> TensorDict:
        """One scan ``z [B, 3]`` (NaN = missed detection), one row per track: the tracks of the last ``reset`` (the first
        scan without one sets their number; a scan of another number of rows is refused); ``reset [B]`` bool restarts
        those tracks;
        ``dt`` the time since each track's previous scan (a number or ``[B]``, seconds; None: the
        network's ``net.dt``), checked against the intervals the network was trained at
        (:func:`check_dt`) and passed to ``IMMNet.scan`` as its ``interval``: for a network trained over a range, an
        interval longer than it is coasted through at equal intervals inside it, missed scans before this one
        (:func:`coast_scan`, as ``track`` cuts a long gap), and a track's first scan after a reset takes its interval
        as nominal (at most the range's end, as ``track``'s scan 0). A track with no detection for longer than
        ``max_coast`` seconds (the CSV path's coasting limit, 30 s by default) restarts at this scan, as with ``reset``,
        its first scan at the interval of its scan before: a long interval costs one scan. ``r`` each track's measurement std (a
        number or ``[B]``, metres), for a network whose filter experts are told it (``r="data"``). Over a sequence,
        ``track``'s numbers.

        The outputs of a track that has had no detection yet are NaN; a gated measurement (module doc)
        is a missed detection and adds one to ``n_gated``. Where the experts carry a covariance
        (``net.has_cov``) the output holds the fused state's, ``("fused", "cov")`` ``[B, 9, 9]``, as the network
        reports it (``IMMNet.reported_cov``: times its consistency scale where it keeps one); the paper's
        KalmanNet experts give none (no such key).

        ``R [B, 3, 3]``: each detection's measurement covariance (m^2; a NaN matrix where the track has no detection),
        e.g. a radar plot's (``immnet.data.csvio``). It is checked (its shape, and symmetric positive definite where
        the track has a detection: a ValueError otherwise). A network whose filter experts are told it
        (``FilterGain(r="detection")``, ``net.start.told_cov``) filters with it, and needs it at every scan; any other
        **does not use** it (the shipped ones estimate each track's noise from its measurements, ``r`` tells a
        told-``r`` network one std per track): a UserWarning says so. The model-based filters read it from a batch's
        ``meas_cov`` (``immnet track --method``).
        """
        z = as_measurements(z, 2)
        self._check_told(r)  # before anything of the tracker's state changes
        told_cov = self.net.start.told_cov
        if told_cov and R is None:
            raise ValueError("this network's filter experts are told each detection's measurement covariance "
                             "(r='detection'): give Tracker.step its R [n_tracks, 3, 3]")
        cov = None if R is None else check_meas_cov(R, z)
        if R is not None and not told_cov:
            warnings.warn("Tracker.step: this network does not use R (each detection's covariance): it was checked and "
                          "left unused (docs/radar.md, 'Input')", UserWarning, stacklevel=3)
        held = None if self.carry is None else self.carry.batch_size[0]
        gated, n_gated, mask, first, now, since = begin_scan(self, z, reset, dt, self.net.dt, held)
        told = None if r is None else per_track(r, z.shape[0], "r", torch.float32)
        if dt is not None:  # checked as the network takes it, before anything of the tracker's state changes
            cuts, each = check_scan(self.net, now, first, "this tracker")
        if self.carry is None:  # the first scan without a reset: its number of tracks
            self.reset(z.shape[0])
        origin = next_origin(self.origin, gated, mask, self._guarded)
        z = to_local(gated, origin.nan_to_num())
        self.n_gated += n_gated
        self.since, self.origin, self.last = since, origin, now
        if mask is not None:
            self.carry = select_rows(mask, self.net.initial_carry(z.shape[0]), self.carry)
        cov = None if not told_cov else torch.where(torch.isnan(z).any(-1)[:, None, None], torch.eye(3, dtype=cov.dtype),
                                                     cov).to(z.dtype)
        if dt is None:
            self.carry = self.net.scan(self.carry, z, r=told, meas_cov=cov)
        else:
            keep = lambda td: td.select(*self.net.carry_keys)  # noqa: E731
            self.carry = coast_scan(self.net, self.carry, z, cuts, each, keep, told, cov)[1]
        self.fresh = torch.zeros_like(first)
        out = self.carry.select(keys.EXPERT_PROBS, keys.EXPERT_POST).clone()
        out.set(keys.FUSED, self.net.estimate(self.carry).clone())  # the output correction's, where it has one
        if self.net.has_cov:
            out.set(keys.FUSED_COV, self.net.reported_cov(self.carry).clone())
        out.set(keys.MODE_PROBS, self.net.to_mode_probs(out.get(keys.EXPERT_PROBS)))
        out = outputs_to_world(out, origin.nan_to_num())
        waiting = (self.carry.get(keys.AGE) == 0)[:, None]  # no detection yet: no estimate
        return out.apply(lambda v: blank_before_first_detection(v.unsqueeze(1), waiting).squeeze(1))

    def _check_told(self, r) -> None:
        """An ``r`` given to a network that estimates it is refused, not ignored."""
        if r is not None and not self.net.start.told_r:
            raise ValueError("this network estimates each track's measurement std itself; to tell it, load it with "
                             "r='data' (each track's, given here) or one number: Tracker.pretrained(name, r=...), "
                             "load_network(path, r=...)")

    @torch.no_grad()
    def track(self, measurements: torch.Tensor, batch_size: int = 512, intervals: torch.Tensor | None = None,
              return_cov: bool = False, r: torch.Tensor | None = None, return_loglik: bool = False,
              meas_cov: torch.Tensor | None = None) -> TensorDict:
        """Whole sequences ``[B, T, 3]`` -> ``state [B, T, 9]``, ``mode_probs [B, T, 4]``, ``expert_probs``,
        ``expert_post``, ``mode_logits`` and, with ``return_cov``, ``state_cov [B, T, 9, 9]`` (the fused
        covariance; a ValueError saying why where the experts carry none, ``net.has_cov``), NaN before each
        track's first detection; ``n_gated`` counts the measurements gated in this call (module doc).
        ``intervals [B, T]``: the interval before each scan (``immnet.data.times.scan_intervals``; None: the
        network's ``dt``), each one the network was trained at (:func:`check_dt`), except that for a network trained
        over a range an interval longer than it is a gap the track coasts through at intervals inside it
        (:func:`coast_long_gaps`; the output holds the scans given); a track with no detection for longer than
        ``max_coast`` seconds restarts there, as in ``step`` (the parts between restarts tracked as fresh tracks). ``r [B]``: each track's measurement std, for a network whose filter experts are told it
        (``FilterGain(r="data")``). ``return_loglik``: also each scan's
        measurement log-likelihood under the network's prediction, ``loglik [B, T]`` (``IMMNet.predictive_loglik``).
        ``meas_cov [B, T, 3, 3]``: each detection's covariance, for a network whose filter experts are told it
        (``FilterGain(r="detection")``; ``IMMNet.told_cov`` of a batch)."""
        z = as_measurements(measurements, 3)
        self._check_told(r)
        if meas_cov is not None and not self.net.start.told_cov:
            raise ValueError("this network is not told each detection's covariance (its filter gain's r is not "
                             "'detection'): give it no meas_cov")
        if meas_cov is not None and tuple(meas_cov.shape) != (*z.shape[:2], 3, 3):
            raise ValueError(f"meas_cov is [n_tracks, T, 3, 3] = {[*z.shape[:2], 3, 3]}, got {list(meas_cov.shape)}")
        if return_cov and not self.net.has_cov:
            raise ValueError(self.net.no_cov_reason())
        told = None if r is None else per_track(r, z.shape[0], "r", torch.float32)

        def run(zs, ivs, rows):  # a track, or a segment of one (its detections' covariances after its measurements)
            cov = None if meas_cov is None else zs[..., 3:].unflatten(-1, (3, 3))
            return run_network(self.net, zs[..., :3], batch_size, ivs, return_cov,
                               told if told is None or rows is None else told[rows], return_loglik, self.max_position,
                               cov)[0]

        rows = z if meas_cov is None else torch.cat([z, torch.as_tensor(meas_cov).to(z.dtype).flatten(-2)], -1)
        return by_segments(self, run, rows, intervals, self.net.dt)
