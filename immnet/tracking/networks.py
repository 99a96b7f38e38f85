"""Loading a trained IMMNet and running it over whole sequences: what the streaming ``Tracker`` and the bank of
networks (``immnet.tracking.bank``) share (``load_network``, ``read_checkpoint``, the interval checks, ``run_network``).
"""

from __future__ import annotations

import copy
import math
import numbers
import re
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from immnet import keys
from immnet.checkpoints import CheckpointError, load_checkpoint, shipped_entry
from immnet.config import import_class
from immnet.data.validate import MAX_ABS_POSITION, gate_measurements
from immnet.filters.base import before_first_detection, blank_before_first_detection
from immnet.imm.guard import AS_CONFIGURED
from immnet.motion import POS_VIEW
from immnet.stages import IMMNet
from immnet.stages.base import Stage
from immnet.stages.network import DEFAULT_GAIN, _where, net_arguments



def read_checkpoint(path: str | Path) -> tuple[dict, dict]:
    """The ``net`` config and the IMMNet weights (``net.`` prefix removed) of a Lightning checkpoint or
    exported weights, read by ``immnet.checkpoints.load_checkpoint`` (plain data only, checksum verified);
    a one-line error naming the file for a missing, unreadable, unsafe, altered or foreign one."""
    path = Path(path)
    ckpt = load_checkpoint(path)
    if not (isinstance(ckpt.get("state_dict"), dict) and isinstance(ckpt.get("hyper_parameters"), dict)):
        raise ValueError(f"{path} is not an IMMNet checkpoint (no state_dict / hyper_parameters)")
    config = ckpt["hyper_parameters"].get("net") or {}
    if not isinstance(config, dict):
        raise ValueError(f"{path} is not an IMMNet checkpoint (its hyper_parameters' net is a {type(config).__name__})")
    state = {k[len("net."):]: v for k, v in ckpt["state_dict"].items() if isinstance(k, str) and k.startswith("net.")}
    check_finite(state, path)
    try:
        return net_arguments(copy.deepcopy(config), saved=True), state
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None


def check_finite(state: dict, path) -> None:
    """A ``CheckpointError`` naming ``path`` and the first weight (in the file's order) that holds a NaN or an
    infinity: a network that diverged in training, whose checksum can be valid, would track to NaN."""
    for name, value in state.items():
        if isinstance(value, torch.Tensor) and value.is_floating_point():
            bad = int((~torch.isfinite(value)).sum())
            if bad:
                raise CheckpointError(f"{path}: its weight net.{name} holds {bad} non-finite value(s) (NaN or inf) of "
                                      f"{value.numel()}: weights that diverged in training cannot track")


def fit_weights(net: torch.nn.Module, state: dict, path) -> None:
    """Load ``state`` into ``net`` (strict); a ``CheckpointError`` naming ``path`` and the first weight that
    differs (one of another shape, one the network has no place for, one the file lacks) where the file's weights
    are of another architecture than the network its config builds."""
    try:
        net.load_state_dict(state)
        return
    except RuntimeError as err:
        text = str(err)
    own = net.state_dict()
    shaped = [k for k in state if k in own and tuple(state[k].shape) != tuple(own[k].shape)]
    extra = re.search(r'Unexpected key\(s\) in state_dict: "([^"]+)"', text)
    missing = re.search(r'Missing key\(s\) in state_dict: "([^"]+)"', text)
    if shaped:
        why = f"net.{shaped[0]} is {list(state[shaped[0]].shape)} in the file, {list(own[shaped[0]].shape)} in the network"
    elif extra:
        why = f"the network has no weight net.{extra.group(1)}"
    elif missing:
        why = f"the file has no weight net.{missing.group(1)}"
    else:
        why = text.strip().splitlines()[-1].strip()
    raise CheckpointError(f"{path}: its weights are of another architecture than the network its config builds "
                          f"({why})")


_NEEDS_FILTERS = {"guard": "a range guard", "adapt": "adaptive process noise", "r": "a measurement std",
                  "reacquire": "re-acquisition", "robust": "a robust update",
                  "start_vz_std": "a start's prior on the vertical speed"}  # each: "... needs filter experts"


def load_network(path: str | Path, guard=AS_CONFIGURED, adapt=AS_CONFIGURED, r=AS_CONFIGURED,
                 reacquire=AS_CONFIGURED, robust=AS_CONFIGURED, start_vz_std=AS_CONFIGURED) -> IMMNet:
    """Rebuild the IMMNet of a Lightning checkpoint (stage 1 or stage 2) with its weights.

    ``guard``: the checkpoint's range guard (``"checkpoint"``), none (``None``), or another region
    (``True`` for 3D-LAST's, or a dict of ``RangeGuard`` fields); it has no weights, so any choice loads.
    ``adapt``: the filter experts' adaptive process noise (``immnet.imm.adaptive.AdaptiveNoise``), as
    the checkpoint has it (``"checkpoint"``), off (``None``/``False``), on (``True``) or a dict of its
    fields; no weights either.
    ``r``: the filter experts' measurement std (m), as the checkpoint has it (``"checkpoint"``), estimated from each
    track's measurements (``None``), one number for every track (a radar that knows its accuracy), or told per
    track (``"data"``: the step's input ``"r"``, ``Tracker.track(r=...)``); no weights either
    (``FilterGain``'s ``r``; docs/tracking.md "A radar that knows its accuracy").
    ``reacquire``: the filter experts' re-acquisition (``FilterGain``'s, ``immnet.imm.reacquire``), as the checkpoint
    has it (``"checkpoint"``), off (None) or a dict of its fields; no weights either. ``robust``: the filter experts'
    Huber update (``FilterGain``'s ``robust``, ``immnet.imm.kalman``), as the checkpoint has it (``"checkpoint"``), off
    (None) or its ``k``; no weights either (modes per group refuse it). ``start_vz_std``: the filter experts' prior on
    a track's vertical speed at its start (``FilterGain``'s), as the checkpoint has it, off (None) or its std (m/s).
    """
    return network_from(*read_checkpoint(path), path, guard, adapt, r, reacquire, robust, start_vz_std)


def network_from(config: dict, state: dict, path, guard=AS_CONFIGURED, adapt=AS_CONFIGURED, r=AS_CONFIGURED,
                 reacquire=AS_CONFIGURED, robust=AS_CONFIGURED, start_vz_std=AS_CONFIGURED) -> IMMNet:
    """``load_network``'s IMMNet from a checkpoint read already (``read_checkpoint``'s ``config`` and ``state``, of
    the file ``path``, named in its errors)."""
    for name, value in (("guard", guard), ("adapt", adapt), ("r", r), ("reacquire", reacquire), ("robust", robust),
                        ("start_vz_std", start_vz_std)):
        if isinstance(value, str) and value == AS_CONFIGURED:
            continue
        gain = config.get("gain") or DEFAULT_GAIN
        if name not in import_class(gain.get("class_path", ""), Stage).load_options:
            raise ValueError(f"{path}: {_NEEDS_FILTERS[name]} needs filter experts; this checkpoint's gain is "
                             f"{gain.get('class_path')}")
        config.pop(name, None)  # set once: on the gain, for this load
        config["gain"] = {**gain, "init_args": {**(gain.get("init_args") or {}), name: value}}
    net = IMMNet(**config)
    fit_weights(net, state, path)
    return net.eval()


def trained_for(net, intervals) -> torch.Tensor:
    """Elementwise, whether each interval (s) is one ``net`` was trained at: inside its ``interval_range`` (to 1e-6 of
    the range's end), or its one ``dt`` (to 1e-6 of it); NaN is not. The rule of :func:`check_dt`, per interval."""
    iv = torch.as_tensor(intervals, dtype=torch.float64)
    span = getattr(net, "interval_range", None)
    lo, hi = (float(span[0]), float(span[1])) if span is not None else (float(net.dt), float(net.dt))
    tol = 1e-6 * max(1.0, hi)
    return (iv >= lo - tol) & (iv <= hi + tol)


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
    bad = listed([f"{v:g}" for v in values[~trained_for(net, values)].tolist()])
    span = getattr(net, "interval_range", None)
    others = "a method that takes any interval: the model-based ones, e.g. --method imm-tuned"
    if bad and span is not None:
        raise ValueError(
            f"{name} was trained on intervals {float(span[0]):g}-{float(span[1]):g} s but this data has an interval of "
            f"{bad} s, outside that range; resample the data, train a model over this range (DataSpec dt), or use "
            f"{others}")
    if bad:
        raise ValueError(
            f"{name} was trained on data sampled at dt = {net.dt:g} s but this data has dt = {bad} s; it was trained "
            f"at that one interval only, and a learned tracker only knows its training interval (its velocities would "
            f"be off by the ratio): resample the data to dt = {net.dt:g} s, train a model at this dt (DataSpec dt), or "
            f"use {others}")


def listed(values) -> str:
    """``values`` as a refusal lists them: the first five, comma-separated, then ``, ...`` where there are more."""
    return ", ".join(map(str, values[:5])) + (", ..." if len(values) > 5 else "")


def coast_cuts(net, intervals, first=None) -> tuple[torch.Tensor, torch.Tensor]:
    """``(scans, each)``: how many scans ``net`` takes each interval (s) in, and each scan's interval, as
    :func:`coast_long_gaps` cuts a sequence's: for a network trained over a range, an interval longer than the range
    is ``ceil(interval / end)`` equal intervals inside it, the scans before the last missed detections (a gap the
    track coasts through); where ``first`` (bool, broadcasting to the intervals' shape: a track's first scan, whose
    interval is the nominal one) it is one scan of at most the range's end. Otherwise one scan of the interval as
    given (NaN too)."""
    iv = torch.as_tensor(intervals, dtype=torch.float64)
    span = getattr(net, "interval_range", None)
    if span is None:
        return torch.ones(iv.shape, dtype=torch.long), iv
    hi = float(span[1])
    if first is not None:
        iv = torch.where(torch.as_tensor(first, dtype=torch.bool), iv.clamp(max=hi), iv)
    end = hi + 1e-6 * max(1.0, hi)  # trained_for's tolerance, as segments._scan_times'
    if not bool((iv > end).any()):  # nothing to cut (NaN neither)
        return torch.ones(iv.shape, dtype=torch.long), iv
    cuts = torch.ceil(iv / end).clamp(min=1)
    cuts = torch.where(torch.isnan(cuts), torch.ones_like(cuts), cuts)
    return cuts.long(), iv / cuts


def check_scan(net, interval: torch.Tensor, first: torch.Tensor, name: str) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`coast_cuts` of one scan's ``interval [B]`` (``first [B]``: a track's first scan), checked: a ValueError
    (:func:`check_dt`, naming the intervals as given) unless ``net`` was trained at every interval it is cut into."""
    cuts, each = coast_cuts(net, interval, first)
    bad = ~trained_for(net, each)
    check_dt(net, interval[bad] if bool(bad.any()) else each, name)
    return cuts, each


def coast_scan(net: IMMNet, carry: TensorDict, z: torch.Tensor, cuts: torch.Tensor, each: torch.Tensor, keep,
               r: torch.Tensor | None = None, meas_cov: torch.Tensor | None = None) -> tuple[TensorDict, TensorDict]:
    """One scan ``z [B, 3]`` of ``net`` as :func:`run_network` runs it inside a sequence: each track's interval since
    its previous scan as :func:`coast_cuts` cut it, ``cuts [B]`` scans of ``each [B]`` s, the track coasting through
    the missed scans before its detection, ``keep(after)`` what it carries from one to the next. Returns ``(before,
    after)``: the carry the scan of ``z`` starts from (``carry`` where nothing was cut) and that scan's output. ``r
    [B]``: each track's measurement std, for a network told it; ``meas_cov [B, 3, 3]`` the detection's covariance, for a
    network told it (the missed scans before it read none). The caller checks the intervals (:func:`check_dt`)."""
    each = each.to(z.dtype)

    def scan(c, zz):
        return net.scan(c, zz, interval=None if bool((each == net.dt).all()) else each, r=r, meas_cov=meas_cov)

    missed = torch.full_like(z, float("nan"))
    for i in range(int(cuts.max()) - 1 if len(cuts) else 0):  # the missed scans, each track's before its detection
        coasting = cuts > i + 1
        after = keep(scan(carry, missed))  # the whole batch, as in a sequence (a batch's size moves float32 rounding)
        carry = after if bool(coasting.all()) else select_rows(coasting, after, carry)
    return carry, scan(carry, z)


def coast_long_gaps(net, z: torch.Tensor, intervals: torch.Tensor):
    """``(z, intervals, where)`` for a network trained over a range of intervals (``net.interval_range``): every
    interval longer than the range cut into equal intervals inside it by missed scans (:func:`coast_cuts`, as the
    CSV path cuts a gap, ``segments._scan_times``: a gap is a gap, the track coasts through it), ``where [B, T]``
    (numpy) the input's scans among the new ones (None where nothing is cut); scan 0's interval (a track's start) at
    most the range's end. A track with fewer scans than the longest continues with missed scans at the range's end
    (whose estimates no one reads). For a network of one interval, the input and None. ``z`` may carry more per scan
    than its measurement (``[B, T, ...]``: what the scan's rows hold, NaN in the missed scans cut in)."""
    span = getattr(net, "interval_range", None)
    if span is None:
        return z, intervals, None
    cuts, each = coast_cuts(net, intervals, torch.arange(intervals.shape[-1]) == 0)  # scan 0: a track's start
    if not bool((cuts > 1).any()):
        return z, each, None  # scan 0's at most the range's end
    where = cuts.cumsum(-1) - 1  # each scan is the last of its interval's
    B, width = z.shape[0], int(where[:, -1].max()) + 1
    full = torch.full((B, width, *z.shape[2:]), float("nan"), dtype=z.dtype)
    steps = torch.full((B, width), float(span[1]), dtype=torch.float64)
    for b in range(B):
        n = int(where[b, -1]) + 1
        full[b, where[b]] = z[b]
        steps[b, :n] = torch.repeat_interleave(each[b], cuts[b])
    return full, steps, where.numpy()


# --- the local frame: each track tracked around its first detection, so that float32 keeps its digits anywhere -----
WORLD = (keys.STATE, keys.ROLLOUT_EXPERT_POST, keys.FUSED, keys.EXPERT_POST)  # outputs that hold positions


def frame_origin(net, z: torch.Tensor) -> torch.Tensor:
    """Each track's origin ``[B, 3]`` (float64) in ``z [B, T, 3]`` (gated measurements, NaN rows missed): its first
    detection (zero for a track with none). A network with a range guard (:func:`guarded`) keeps the radar's frame,
    origin zero: its guard's rules read radar-centred positions (3D-LAST's region, tens of km, where float32 keeps
    millimetres)."""
    origin = torch.zeros(z.shape[0], 3, dtype=torch.float64)
    if guarded(net):
        return origin
    seen = ~torch.isnan(z).any(-1)
    has = seen.any(-1)
    first = seen.to(torch.uint8).argmax(-1)
    origin[has] = z[has, first[has]].to(torch.float64)
    return origin


def next_origin(origin: torch.Tensor, z: torch.Tensor, reset: torch.Tensor | None,
                radar: bool = False) -> torch.Tensor:
    """The streaming trackers' :func:`frame_origin` after one scan ``z [B, 3]`` (gated): ``origin [B, 3]`` (NaN: the
    track has had no detection since its start or restart; ``reset [B]``, or None: the tracks that restart at this
    scan) set to this scan's detection where it has none yet; zero where the network keeps the radar's frame
    (``radar``: it has a range guard)."""
    if radar:
        return torch.zeros_like(origin)
    origin = origin if reset is None else torch.where(reset[:, None], float("nan"), origin)
    new = torch.isnan(origin).any(-1) & ~torch.isnan(z).any(-1)
    return torch.where(new[:, None], z.to(torch.float64), origin)


def to_local(z: torch.Tensor, origin: torch.Tensor) -> torch.Tensor:
    """Measurements ``z [B, (T,) 3]`` in each track's frame, ``z - origin [B, 3]`` in float64, then as the network's
    float32 (NaN rows stay NaN)."""
    at = origin.view(origin.shape[0], *([1] * (z.dim() - 2)), 3)
    return (z.to(torch.float64) - at).to(torch.float32)


def to_world(v: torch.Tensor, origin: torch.Tensor) -> torch.Tensor:
    """States ``v [B, ..., 9]`` of each track's frame back in the caller's: the position components plus ``origin
    [B, 3]`` in float64 (the output is float64; velocities and accelerations as the network gave them)."""
    at = origin.view(origin.shape[0], *([1] * (v.dim() - 2)), 3)
    v = v.to(torch.float64).clone()
    v[..., POS_VIEW] = v[..., POS_VIEW] + at
    return v


def outputs_to_world(out: TensorDict, origin: torch.Tensor) -> TensorDict:
    """``out``'s states (``WORLD``: the fused state, each expert's posterior) back in the caller's frame
    (:func:`to_world`); covariances, probabilities and likelihoods are the same in either frame."""
    for k in WORLD:
        if k in out.keys(True, True):
            out.set(k, to_world(out.get(k), origin))
    return out


@torch.no_grad()
def run_network(net: IMMNet, z: torch.Tensor, batch_size: int = 512, intervals: torch.Tensor | None = None,
                return_cov: bool = False, r: torch.Tensor | None = None, return_loglik: bool | str = False,
                max_position: float = MAX_ABS_POSITION, meas_cov: torch.Tensor | None = None) -> tuple[TensorDict, int]:
    """``Tracker.track``'s work, ``(outputs, n_gated)``: ``z [B, T, 3]`` (float64, or float32) gated (``max_position``)
    and moved into each track's frame (:func:`frame_origin`, :func:`to_local`: float32 from there), a gap longer than
    a range network's range cut into missed scans (:func:`coast_long_gaps`), every interval checked
    (:func:`check_dt`), ``net.rollout`` in batches of ``batch_size`` tracks, ``mode_probs`` added, NaN before each
    track's first detection, the scans asked for returned and the states back in the caller's frame (float64,
    :func:`outputs_to_world`). ``meas_cov [B, T, 3, 3]``: each detection's covariance, for a network told it (a
    translation of the frame leaves it as it is)."""
    z, n_gated = gate_measurements(z, max_position)
    origin = frame_origin(net, z)
    z = to_local(z, origin)
    where, cov = None, None if meas_cov is None else torch.as_tensor(meas_cov).to(z.dtype)
    if intervals is not None:  # each detection's covariance moves with its scan
        rows = z if cov is None else torch.cat([z, cov.flatten(-2)], -1)
        rows, intervals, where = coast_long_gaps(net, rows, as_intervals(intervals, z))
        z, cov = rows[..., :3], None if cov is None else rows[..., 3:].unflatten(-1, (3, 3))
        check_dt(net, intervals, "this tracker")
    outs = []
    for i in range(0, z.shape[0], batch_size):
        gaps = None if intervals is None else intervals[i : i + batch_size].to(z.dtype)
        told = None if r is None else torch.as_tensor(r, dtype=z.dtype).reshape(-1)[i : i + batch_size]
        out, _ = net.rollout(z[i : i + batch_size], intervals=gaps, return_cov=return_cov, r=told,
                             return_loglik=return_loglik, meas_cov=None if cov is None else cov[i : i + batch_size])
        out.set(keys.MODE_PROBS, net.to_mode_probs(out[keys.ROLLOUT_EXPERT_PROBS]))
        waiting = before_first_detection(z[i : i + batch_size])
        outs.append(out.apply(lambda v, w=waiting: blank_before_first_detection(v, w)))
    out = torch.cat(outs, 0)
    if where is not None:  # the scans asked for, without the missed ones cut into the long gaps
        out = out[torch.arange(out.batch_size[0])[:, None], torch.from_numpy(where)]
    return outputs_to_world(out, origin), n_gated


def select_rows(mask, a: TensorDict, b: TensorDict) -> TensorDict:
    """``a``'s rows where ``mask`` [B], ``b``'s elsewhere, over ``a``'s keys (a fresh carry for the tracks that
    restart)."""
    return _where(mask, a, b.select(*a.keys(True, True)))


# --- the streaming and whole-sequence APIs' input checks: one line naming what is wrong, before anything changes ----
def as_measurements(z, dims: int) -> torch.Tensor:
    """``z`` as float64 measurements ``[n_tracks, 3]`` (``dims`` 2, a scan) or ``[n_tracks, T, 3]`` (3, sequences):
    float64 until each track is moved into its own frame (:func:`frame_origin`), then the network's float32; a
    ValueError for another shape, no track or no scan, and for booleans or complex numbers (which a cast would turn
    into positions without a word)."""
    raw = z if isinstance(z, torch.Tensor) else torch.as_tensor(np.asarray(z))
    if raw.dtype == torch.bool or raw.is_complex():
        raise ValueError(f"measurements are real numbers of metres, got {raw.dtype}".replace("torch.", ""))
    z = raw.to(torch.float64)
    shape = "[n_tracks, 3]" if dims == 2 else "[n_tracks, T, 3]"
    what = "a scan of measurements is" if dims == 2 else "measurements are"
    if z.dim() != dims or z.shape[-1] != 3:
        raise ValueError(f"{what} {shape}, got {tuple(z.shape)}")
    if z.shape[0] == 0 or (dims == 3 and z.shape[1] == 0):
        raise ValueError(f"{what} {shape} with at least one track{'' if dims == 2 else ' and one scan'}, "
                         f"got {tuple(z.shape)}")
    return z


def as_intervals(intervals, z: torch.Tensor) -> torch.Tensor:
    """``intervals`` as float64 ``[n_tracks, T]`` of sequences ``z [n_tracks, T, ...]``; a ValueError for another
    shape."""
    iv = torch.as_tensor(intervals, dtype=torch.float64)
    if tuple(iv.shape) != tuple(z.shape[:2]):
        raise ValueError(f"intervals are [n_tracks, T] = {tuple(z.shape[:2])}, got {tuple(iv.shape)}")
    return iv


def check_n_tracks(n_tracks) -> int:
    """``n_tracks`` as an int; a ValueError unless it is a whole number of at least 1 (a bool is not one)."""
    if isinstance(n_tracks, (bool, np.bool_)) or not isinstance(n_tracks, (numbers.Integral, torch.Tensor)) \
            or (isinstance(n_tracks, torch.Tensor) and (n_tracks.numel() != 1 or n_tracks.dtype.is_floating_point
                                                        or n_tracks.dtype == torch.bool)) or int(n_tracks) < 1:
        raise ValueError(f"reset(n_tracks) takes a whole number of tracks, at least 1, got {n_tracks!r}")
    return int(n_tracks)


def per_track(value, n: int, name: str, dtype=torch.float64) -> torch.Tensor:
    """``value`` (one number or one per track) as ``[n]``; a ValueError naming both lengths otherwise."""
    v = torch.as_tensor(value, dtype=dtype).reshape(-1)
    if v.numel() not in (1, n):
        raise ValueError(f"{name} has {v.numel()} values for {n} tracks: give one, or one per track")
    return v.expand(n)


def check_finite_intervals(intervals: torch.Tensor, name: str) -> torch.Tensor:
    """``intervals``, checked: a ValueError naming the first NaN or infinite one (``[B]`` a step's ``dt``, ``[B, T]`` a
    sequence's); ``check_dt`` refuses the other intervals a network was not trained at (0, negative)."""
    bad = ~torch.isfinite(intervals)
    if bool(bad.any()):
        where = bad.nonzero()[0].tolist()
        at = f"track {where[0]}" + (f", scan {where[1]}" if len(where) > 1 else "")
        raise ValueError(f"{name} is {float(intervals[tuple(where)]):g} at {at}: the time since a track's previous scan "
                         f"is a number of seconds")
    return intervals


def on_cpu(net, who: str):
    """``net``, refused in one line unless its weights and buffers are on the CPU: the trackers keep each track's
    frame, intervals and coasting (``frame_origin``, ``begin_scan``, ``coast_long_gaps``) as CPU tensors."""
    devices = sorted({str(t.device) for t in (*net.parameters(), *net.buffers())} - {"cpu"})
    if devices:
        raise ValueError(f"{who} runs on the CPU; this network is on {', '.join(devices)}: give it net.cpu()")
    return net


def guarded(net) -> bool:
    """Whether ``net`` keeps a range guard (``immnet.imm.guard``: its rules read positions as radar-centred)."""
    return any(getattr(m, "guard", None) is not None for m in net.modules())


def scans_served(net) -> str:
    """The scan intervals a network was trained for, as the trackers name them: ``0.5-12 s`` or ``1 s``."""
    span = getattr(net, "interval_range", None)
    return f"{span[0]:g}-{span[1]:g} s" if span is not None else f"{net.dt:g} s"


def provenance_of(path) -> str:
    """Where shipped weights' provenance is (the weights table's ``PROVENANCE-NAME.md``: ``immnet.checkpoints``),
    else the checkpoint's path (a network of one's own: no provenance shipped)."""
    if path is None:
        return "no provenance (built in Python)"
    entry = shipped_entry(path)
    if entry is not None:
        return f"provenance immnet/pretrained/{entry['provenance']}"
    return f"no provenance shipped (checkpoint {path})"


# --- the coasting limit: a track with no detection for longer than ``max_coast`` seconds restarts ---------------------
def coast_restarts(detected: torch.Tensor, intervals: torch.Tensor, max_coast: float):
    """``(restart, taken)``: ``restart [B, T]`` bool, the scans at which a track restarts, as ``Tracker.step`` restarts
    it (:func:`coast_step`): where the time since its last detection (or its start) would pass ``max_coast`` seconds;
    ``taken [B, T]`` the intervals as the trackers take them: a restarted track's first scan at the interval of the
    scan before it (the time before a restart is none the track coasts through). ``detected [B, T]``: the scans with
    a detection (after the gate), ``intervals [B, T]`` (s) the interval before each scan (scan 0's a track's start)."""
    B, T = detected.shape
    since = torch.zeros(B, dtype=torch.float64)
    restart = torch.zeros(B, T, dtype=torch.bool)
    if not math.isfinite(max_coast):
        return restart, intervals
    taken = intervals.clone()
    for t in range(1, T):
        since, restart[:, t] = coast_step(since, intervals[:, t], detected[:, t], None, max_coast)
        taken[:, t] = torch.where(restart[:, t], taken[:, t - 1], intervals[:, t])
    return restart, taken


def coast_step(since: torch.Tensor, interval: torch.Tensor, detected: torch.Tensor, first, max_coast: float):
    """``(since, restart)`` after one scan: ``restart [B]`` where a track that is not at its first scan (``first``,
    None: none is) has had no detection for longer than ``max_coast`` s by this scan; ``since [B]`` the seconds since
    each track's last detection, its start or its restart, after it."""
    total = since + interval
    # past max_coast to 1e-9 of it (times summed from intervals round; the CSV path's segments, segments._join, keep a
    # gap of exactly max_coast in its track)
    restart = total > max_coast * (1 + 1e-9) if math.isfinite(max_coast) else torch.zeros_like(detected)
    if first is not None:
        restart = restart & ~first
        total = torch.where(first, torch.zeros_like(total), total)
    return torch.where(restart | detected, torch.zeros_like(total), total), restart


def fresh_tracks(tracker, n_tracks: int) -> None:
    """The per-track memory a streaming tracker (``Tracker``, ``NetworkBank``) keeps beside its carry, for ``n_tracks``
    tracks that have not started: ``fresh`` (no scan yet: the first one's interval is nominal), ``since`` (s since the
    last detection or the start: ``max_coast``'s), ``last`` (the interval of the last scan; NaN: none yet) and
    ``origin`` (the track's frame, :func:`next_origin`; NaN: no detection yet); ``n_gated`` back to 0."""
    tracker.fresh = torch.ones(n_tracks, dtype=torch.bool)
    tracker.since = torch.zeros(n_tracks, dtype=torch.float64)
    tracker.last = torch.full((n_tracks,), float("nan"), dtype=torch.float64)
    tracker.origin = torch.full((n_tracks, 3), float("nan"), dtype=torch.float64)
    tracker.n_gated = 0


def begin_scan(tracker, z: torch.Tensor, reset, dt, nominal: float, held: int | None):
    """What a streaming tracker (``Tracker``, ``NetworkBank``: its ``fresh``, ``since``, ``last``, ``max_position`` and
    ``max_coast``; ``held``: the number of tracks it holds, None: none yet) reads of one scan ``z [B, 3]`` (a row per
    track held; a ValueError for another number) before anything of its state changes:
    ``(gated, n_gated, reset, first, now, since)``: ``z`` gated, the number gated, ``reset [B]`` (None: none) the
    tracks that restart at this scan, given or after no detection for longer than ``max_coast`` s (:func:`coast_step`),
    ``first [B]`` each track's first scan since a restart, ``now [B]`` the scan's interval (``dt``, a number or ``[B]``;
    None: ``nominal``), a restarted track's at the interval of its scan before where ``dt`` is given, and ``since [B]``
    after the scan."""
    B, started = z.shape[0], held is not None
    if started and held != B:
        raise ValueError(f"this tracker holds {held} tracks but the scan has {B} rows: give one row per track (NaN for "
                         f"a missed detection), or reset({B}) first")
    reset = None if reset is None else per_track(reset, B, "reset", torch.bool)
    first = tracker.fresh if started else torch.ones(B, dtype=torch.bool)
    first = first if reset is None else first | reset
    now = torch.full((B,), float(nominal), dtype=torch.float64) if dt is None else per_track(dt, B, "dt")
    check_finite_intervals(now, "dt")
    gated, n_gated = gate_measurements(z, tracker.max_position)
    since = tracker.since if started else torch.zeros(B, dtype=torch.float64)
    since, restart = coast_step(since, now, ~torch.isnan(gated).any(-1), first, tracker.max_coast)
    if bool(restart.any()):  # no detection for longer than max_coast: the track starts again, as after a reset,
        reset = restart if reset is None else reset | restart  # its first scan at the interval of the scan before
        first = first | restart
        now = now if dt is None else torch.where(restart, tracker.last, now)
    return gated, n_gated, reset, first, now, since


def by_segments(tracker, run, z: torch.Tensor, intervals, nominal: float) -> TensorDict:
    """``run(z, intervals, rows)`` over whole sequences ``z [B, T, 3 + ...]`` (each scan's measurement, then what else
    the scan carries) as a streaming tracker's ``track`` runs them (``Tracker``, ``NetworkBank``: its ``max_position``
    and ``max_coast``): ``intervals [B, T]`` checked (None: ``nominal`` s at every scan, and None to ``run``); a track
    with no detection for longer than ``max_coast`` s restarts (:func:`coast_restarts`): each part of it between
    restarts run as a fresh track (``rows [S]``: each one's track, None where no track restarts; :func:`_segments`).
    ``tracker.n_gated``: the measurements gated."""
    iv = None if intervals is None else check_finite_intervals(as_intervals(intervals, z), "intervals")
    gated, n_gated = gate_measurements(z[..., :3], tracker.max_position)
    every = torch.full(z.shape[:2], float(nominal), dtype=torch.float64) if iv is None else iv
    restart, taken = coast_restarts(~torch.isnan(gated).any(-1), every, tracker.max_coast)
    out = _segments(run, restart, z, None if iv is None else taken) if bool(restart.any()) else run(z, iv, None)
    tracker.n_gated = n_gated
    return out


def _segments(run, restart: torch.Tensor, z: torch.Tensor, intervals: torch.Tensor | None) -> TensorDict:
    """``run(z [S, L, ...], intervals [S, L] or None, rows [S])`` over each track's segments (a track cut at each scan
    of ``restart [B, T]``, each segment a fresh track from there; ``rows`` each one's track), segments of one length
    together; their outputs put back in place ``[B, T]``."""
    B, T = restart.shape
    starts = restart.clone()
    starts[:, 0] = True
    segs = []  # (track, first scan, length)
    for b in range(B):
        cut = starts[b].nonzero().flatten().tolist() + [T]
        segs += [(b, s, e - s) for s, e in zip(cut[:-1], cut[1:])]
    out = None
    for length in sorted({n for _, _, n in segs}):
        group = [(b, s) for b, s, n in segs if n == length]
        rows = torch.tensor([b for b, _ in group])
        zs = torch.stack([z[b, s : s + length] for b, s in group])
        ivs = None if intervals is None else torch.stack([intervals[b, s : s + length] for b, s in group])
        got = run(zs, ivs, rows)
        if out is None:
            out = TensorDict({k: torch.full((B, T, *v.shape[2:]), float("nan"), dtype=v.dtype)
                              for k, v in got.items(True, True)}, batch_size=[B, T])
        for i, (b, s) in enumerate(group):
            for k, v in got.items(True, True):
                out.get(k)[b, s : s + length] = v[i]
    return out
