"""A bank of trained networks as one tracker: a static multiple-model estimator over whole networks.

Each member network tracks every track it can take (``accepts``: a network trained over a range of scan intervals
takes a track whose every interval lies in the range once an interval longer than the range is cut into missed scans
inside it, as ``Tracker.track`` coasts it; a network trained at one interval takes a track scanned at that interval
throughout), and
the bank reports, scan by scan, the members' estimates weighted by each member's probability for that track: its
prior times the likelihood of the track's measurements under the member's own predictions so far, tempered,

    p_k(t) = p_k(0) prod_{s <= t} p(z_s | z_<s, k)^temper / normalization

(``IMMNet.predictive_loglik``: the member's IMM mixture of its filter experts' innovation likelihoods; by default of
the track as the member reports it, each prediction moved by the member's output correction of the scan before, and
``temper`` 0.5: the shipped bank's ``LIKELIHOOD`` and ``TEMPER``, read with its members and its other settings from
the table of shipped weights, immnet/pretrained/weights.json). This is the
static multiple-model estimator (Magill 1965; Bar-Shalom, Li and Kirubarajan, *Estimation with Applications to
Tracking and Navigation*, 2001, "the static multiple model estimator"): the members are hypotheses about the whole
track (a real aircraft at 1 s, at 5 s, a 3D-LAST target), not about a scan, so, unlike an IMM's modes, no member's
estimate is mixed into another's and each runs as it runs alone. The bank's covariance is the mixture's,
``sum_k p_k (P_k + (x_k - x)(x_k - x)^T)``, its mode probabilities the members' weighted (each reports the same four
data modes), and ``member_probs [B, T, K]`` says which member carries each track.

A member whose probability on a track falls below ``prune`` runs on it no more (``PRUNE``, from a track's
``PRUNE_AFTER``-th scan), and a member may give way, on the tracks another takes, to that one (``DEFER``: the general
network to the 3D-LAST network, at 1 s); where it prunes, ``track`` runs scan by scan (``step``).

Only the scans that every member taking the track predicted are weighed (a member that starts from two detections
predicts from the third); until then the members keep their prior. A scan without a detection weighs nothing. The
members estimate each track's measurement std themselves (a member told it, ``r="data"``, is refused: the bank takes
what a CSV holds). docs/tracking.md "A bank of networks".
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from tensordict import TensorDict

from immnet import keys
from immnet.checkpoints import BANK_MEMBERS, BANK_SETTINGS, SHIPPED, TABLE, shipped
from immnet.data.times import scan_intervals
from immnet.data.validate import MAX_ABS_POSITION, check_limit
from immnet.filters.base import before_first_detection, blank_before_first_detection
from immnet.imm.interaction import moment_match
from immnet.labels import N_MODES
from immnet.motion import Modes
from immnet.stages import IMMNet
from immnet.stages.network import Likelihood
from immnet.tracking.segments import MAX_COAST, check_coast
from immnet.tracking.networks import (
    AS_CONFIGURED, as_measurements, begin_scan, by_segments, check_n_tracks, coast_cuts, coast_scan, fresh_tracks,
    guarded, listed, network_from, next_origin, on_cpu, provenance_of, read_checkpoint, run_network, scans_served,
    select_rows, to_local, to_world, trained_for,
)

DEFAULT_MEMBERS = BANK_MEMBERS
"""The shipped bank (``Tracker.pretrained("bank")``, ``immnet track --weights bank``, the method ``immnet-bank``): the
general network (any interval 0.5-12 s), the real-flight networks at 1 s, 4.5-5.5 s, 10-12 s and any of 4.5-12 s, and
the 3D-LAST network (1 s; in the bank without its range guard, as every member, unless asked), chosen on the validation
sets (docs/tracking.md "A bank of networks")."""


def accepts(net: IMMNet, intervals: torch.Tensor) -> torch.Tensor:
    """Which tracks ``net`` can take, ``[B]`` bool, from each scan's interval ``intervals [B, T]`` (s; scan 0's the
    nominal one, ``immnet.data.times.scan_intervals``), as ``Tracker.track`` would run it: for a network trained over a
    range, every interval inside it once an interval longer than the range is cut into equal ones by missed scans (a
    gap it coasts through, ``immnet.tracking.networks.coast_long_gaps``; scan 0's taken at most the range's end); for
    one trained at one interval, every interval its ``dt`` (``check_dt``'s rule, per track)."""
    intervals = torch.as_tensor(intervals, dtype=torch.float64)
    each = coast_cuts(net, intervals, torch.arange(intervals.shape[-1]) == 0)[1]  # as coast_long_gaps cuts it
    return (trained_for(net, each) | torch.isnan(intervals)).all(-1)


def _mix(log_w: torch.Tensor, state: torch.Tensor, probs: torch.Tensor, cov: torch.Tensor | None,
         ran: list[int] | None = None) -> dict:
    """The members' outputs ``[..., K, ...]`` weighted by ``softmax(log_w [..., K])``: ``state``, ``mode_probs``,
    ``member_probs`` and, given ``cov``, the mixture's covariance ``sum_k p_k (P_k + (x_k - x)(x_k - x)^T)``. A member
    with no weight (-inf: it does not take the track) adds nothing, whatever its output. ``ran``: the members whose
    outputs ``state``, ``probs`` and ``cov`` hold (``[..., len(ran), ...]``, in order), where the others take no track
    (no weight anywhere: they would add nothing)."""
    w_all = torch.softmax(log_w, -1)
    w = w_all if ran is None else w_all[..., ran]
    live = (w > 0)[..., None]
    x = torch.where(live, state, 0.0)
    fused = (w[..., None] * x).sum(-2)
    out = {keys.STATE: fused, keys.MODE_PROBS: (w[..., None] * torch.where(live, probs, 0.0)).sum(-2),
           keys.MEMBER_PROBS: w_all}
    if cov is not None:
        out[keys.STATE_COV] = moment_match(w[..., None, None], x, fused, torch.where(live[..., None], cov, 0.0))
    return out


def _weighed(loglik: torch.Tensor, takes: torch.Tensor) -> torch.Tensor:
    """Each member's weight increment ``[..., K]``: its log-likelihood where every member taking the track predicted
    the scan (all finite among them), else 0."""
    every = (torch.isfinite(loglik) | ~takes).all(-1, keepdim=True)
    return torch.where(every & takes, loglik, torch.zeros((), dtype=loglik.dtype))


_STEP_OUTPUTS = {keys.FUSED: keys.STATE, keys.MODE_PROBS: keys.MODE_PROBS, keys.MEMBER_PROBS: keys.MEMBER_PROBS,
                 keys.FUSED_COV: keys.STATE_COV}
"""``step``'s outputs, each with the name of the mixture's output it is (``_mix``'s, ``track``'s), in ``track``'s
order."""

LIKELIHOODS = Likelihood.spellings()
"""What a member is weighed by (``immnet.stages.network.Likelihood``): its filter's predictive density
(``IMMNet.predictive_loglik``), or the density of the track as it reports it (``reported=True``: the filter's
prediction moved by the member's output correction of the scan before; the shipped bank's, docs/tracking.md "A bank
of networks")."""
# The shipped bank's settings, read from the table of shipped weights (immnet/pretrained/weights.json, "bank"; chosen on
# the validation sets, docs/tracking.md):
LIKELIHOOD = Likelihood.parse(BANK_SETTINGS["likelihood"])
"""What the shipped bank weighs its members by (one of ``LIKELIHOODS``)."""
TEMPER = float(BANK_SETTINGS["temper"])
"""The shipped bank's power of each scan's likelihood."""
PRUNE = float(BANK_SETTINGS["prune"])
"""The shipped bank's pruning: a member whose probability on a track falls below it runs on that track no more."""
PRUNE_AFTER = int(BANK_SETTINGS["prune_after"])
"""No member is pruned from a track in its first scans from its first detection, while the members' likelihoods
still carry their start."""
DEFER = {k: tuple(v) for k, v in BANK_SETTINGS["defer"].items()}
"""The shipped bank's members that give way: the general network does not run on a track the 3D-LAST network takes
(1 s scans), and, the bank's fallback for any interval, is never pruned."""


def _check_defer(defer, names: list[str]) -> dict[str, tuple[str, ...]]:
    """``defer`` (member -> the members it gives way to) as checked: every name a member's, none giving way to itself,
    and none giving way that another gives way to (no chains); a ValueError naming what is wrong."""
    if defer is None:
        return {}
    if not isinstance(defer, dict):
        raise ValueError(f"a bank's defer maps a member to the members it gives way to, got {defer!r}")
    out = {}
    for k, others in defer.items():
        others = (others,) if isinstance(others, str) else tuple(others)
        unknown = [str(n) for n in (k, *others) if n not in names]
        if unknown:
            raise ValueError(f"a bank's defer names {', '.join(unknown)}, not a member ({', '.join(names)})")
        if k in others or not others:
            raise ValueError(f"a bank's member {k!r} gives way to other members, one or more, got {list(others)}")
        out[str(k)] = tuple(map(str, others))
    chained = [k for k in out if any(k in others for others in out.values())]
    if chained:
        raise ValueError(f"bank member {chained[0]!r} both gives way (defer) and is given way to")
    return out


class NetworkBank:
    """Trained networks run side by side on each track and weighed by how well each predicts it (module doc).

    ``members``: name -> ``IMMNet`` (filter experts, each estimating its tracks' r); ``prior``: each member's prior
    probability (default: equal), positive, as many as members. ``likelihood``: ``LIKELIHOODS``; ``temper``: the
    power ``0 < temper <= 1`` of each scan's likelihood (a tempered posterior: members' densities that are too sure of
    themselves weigh less). ``max_position``: the gate on measurements, ``max_coast`` the coasting limit, as
    ``Tracker``'s. ``prune``: a member whose probability on a track falls below it, from the ``prune_after``-th scan
    since the track's first detection, runs on that track no more (never the most probable, never a member that gives
    way); ``defer``: member name -> the members it gives way to, on the tracks they take. None of them here (0, 0,
    none); the shipped bank's (``from_names``' defaults) are ``PRUNE``, ``PRUNE_AFTER`` and ``DEFER``."""

    def __init__(self, members: dict[str, IMMNet], prior=None, max_position: float = MAX_ABS_POSITION,
                 likelihood: str = LIKELIHOOD, temper: float = TEMPER, max_coast: float = MAX_COAST,
                 prune: float = 0.0, defer: dict | None = None, prune_after: int = 0):
        if not (isinstance(prune, (int, float)) and not isinstance(prune, bool) and 0 <= prune < 1):
            raise ValueError(f"a bank's prune is a probability in [0, 1), got {prune!r}")
        if not (isinstance(prune_after, int) and not isinstance(prune_after, bool) and prune_after >= 0):
            raise ValueError(f"a bank's prune_after is a whole number of scans, 0 or more, got {prune_after!r}")
        self.prune, self.prune_after = float(prune), prune_after
        likelihood = Likelihood.parse(likelihood)
        if not (isinstance(temper, (int, float)) and math.isfinite(temper) and 0 < temper <= 1):
            raise ValueError(f"a bank's temper is a number in (0, 1], got {temper!r}")
        self.likelihood, self.temper = likelihood, float(temper)
        if not members:
            raise ValueError("a bank of networks needs at least one member")
        for name, net in members.items():
            if not isinstance(net, IMMNet):
                raise ValueError(f"bank member {name!r} is a {type(net).__name__}, not an IMMNet")
            if net.start.told_r:
                raise ValueError(f"bank member {name!r} is told each track's measurement std (r='data'); a bank's "
                                 f"members estimate it from the measurements")
            if not net.has_cov:
                raise ValueError(f"bank member {name!r} cannot be weighed: {net.no_cov_reason()}")
            on_cpu(net, f"a bank of networks (member {name!r})")
        self.names = list(members)
        self.members = {name: net.eval() for name, net in members.items()}
        self._guarded = {name: guarded(net) for name, net in self.members.items()}  # read at every scan
        self.defer = _check_defer(defer, self.names)
        self._defers = {self.names.index(k): [self.names.index(o) for o in others] for k, others in self.defer.items()}
        self.max_position = check_limit(max_position)
        prior = [1.0] * len(members) if prior is None else [float(p) for p in prior]
        if len(prior) != len(members) or not all(math.isfinite(p) and p > 0 for p in prior):
            raise ValueError(f"a bank's prior is one positive number per member ({', '.join(self.names)}), got {prior}")
        total = sum(prior)
        self.log_prior = torch.tensor([math.log(p / total) for p in prior], dtype=torch.float64)
        self.n_gated = 0
        self.carries, self.log_w, self.fresh = None, None, None  # the streaming state (``reset``, ``step``)
        self.since, self.last, self.origin = None, None, None  # [B] s since each track's last detection (or start): ``max_coast``'s
        self.stays, self.seen = None, None  # [B, K] each member took every scan so far; [B] scans since a detection
        self.max_coast = check_coast(max_coast, self.dt)
        self.paths = {name: None for name in self.names}  # each member's checkpoint, where it was loaded from one
        # no ``interval_range`` of its own: each member cuts a gap longer than its range into scans inside it, so that
        # ``immnet track`` hands the bank each row at its own time, uncut (``track_rows`` without ``max_interval``)

    @classmethod
    def from_names(cls, members=DEFAULT_MEMBERS, prior=None, guard=None, adapt=AS_CONFIGURED, r=AS_CONFIGURED,
                   max_position: float = MAX_ABS_POSITION, likelihood: str = LIKELIHOOD,
                   temper: float = TEMPER, max_coast: float = MAX_COAST, prune: float = PRUNE,
                   defer: dict | None = None, prune_after: int = PRUNE_AFTER, robust=AS_CONFIGURED) -> "NetworkBank":
        """Members by shipped name (``immnet.checkpoints.SHIPPED``) or checkpoint path, each loaded as ``load_network``
        loads it (each file read once) with ``guard`` (default none: no member keeps a range guard unless asked; one
        asked for goes to the members whose modes are the whole target's, since a guard's transitions cannot be per
        axis: ``IMMNet(modes=...)``),
        ``adapt``, ``r`` (one number for every track: a radar that knows its accuracy) and ``robust`` (Huber's ``k`` of
        every member's filter experts, per axis where its modes are); ``likelihood``, ``temper``,
        ``prune``, ``prune_after`` and ``defer``: the bank's (``defer`` None: ``DEFER``'s pairs among these members;
        ``{}`` none)."""
        members = list(members)
        if len(set(map(str, members))) != len(members):
            raise ValueError(f"a bank's members are named once each, got {members}")
        if defer is None:  # the shipped bank's, between the members present
            named = set(map(str, members))
            defer = {k: tuple(o for o in others if o in named) for k, others in DEFER.items() if k in named}
            defer = {k: others for k, others in defer.items() if others}
        nets, paths = {}, {}
        for m in members:  # a shipped network's file by name (``immnet.checkpoints.SHIPPED``), else the path as given
            path = paths[str(m)] = shipped(m) if isinstance(m, str) and m in SHIPPED else Path(m)
            config, state = read_checkpoint(path)
            joint = Modes.parse(config.get("modes", Modes.JOINT)) is Modes.JOINT
            nets[str(m)] = network_from(config, state, path, guard=guard if joint else None, adapt=adapt, r=r,
                                        robust=robust)
        bank = cls(nets, prior, max_position, likelihood, temper, max_coast, prune, defer, prune_after)
        bank.paths = paths
        return bank

    def __repr__(self) -> str:
        """What the bank is: each member by name, the scan intervals it serves, its prior, its range guard and its
        provenance, one line each."""
        prior = torch.exp(self.log_prior).tolist()
        width = max(len(n) for n in self.names)
        lines = [f"  {name:<{width}}  scans of {scans_served(net):<10}  prior {p:.3g}, "
                 f"{'range guard' if guarded(net) else 'no range guard'}; {provenance_of(self.paths[name])}"
                 for (name, net), p in zip(self.members.items(), prior)]
        shipped_bank = set(self.names) == set(DEFAULT_MEMBERS) and all(
            p is not None and provenance_of(p).startswith("provenance") for p in self.paths.values())
        about = f"; provenance immnet/pretrained/{TABLE['bank']['provenance']}" if shipped_bank else ""
        return (f"NetworkBank({len(self.names)} member{'s' if len(self.names) > 1 else ''}, each weighed per track by "
                f"how well it predicts the track: likelihood {self.likelihood.value!r}, temper {self.temper:g}{about}\n"
                + "\n".join(lines) + ")")

    has_cov = True  # every member keeps one (checked when built)

    def no_cov_reason(self) -> str:
        return ""

    def takes(self, intervals: torch.Tensor) -> torch.Tensor:
        """``[B, K]`` bool: which member takes which track: :func:`accepts`, but not a member that ``defer``s to one
        that accepts the track (``_in_track``'s rule over the whole track)."""
        fits = torch.stack([accepts(net, intervals) for net in self.members.values()], -1)
        return self._in_track(fits, fits)[0]

    def check(self, intervals: torch.Tensor, takes: torch.Tensor | None = None, tracks: torch.Tensor | None = None
              ) -> None:
        """A ValueError naming the tracks no member can take, and each member's intervals (``takes``: ``self.takes(
        intervals)`` where the caller has it; ``tracks``: the rows' track numbers, where they are segments)."""
        takes = self.takes(intervals) if takes is None else takes
        lost = (~takes.any(-1)).nonzero().flatten()
        if len(lost):
            named = lost if tracks is None else tracks[lost].unique()
            spans = ", ".join(f"{name} {scans_served(net)}" for name, net in self.members.items())
            iv = torch.as_tensor(intervals, dtype=torch.float64)[lost[0]]
            iv = iv[~torch.isnan(iv)]
            raise ValueError(f"no member of this bank takes track(s) {listed([int(i) for i in named])}: the first has "
                             f"scan intervals of {float(iv.min()):g} to "
                             f"{float(iv.max()):g} s, and its members were trained for {spans}; resample the data, or use "
                             f"a method that takes any interval (the model-based ones, e.g. --method imm-tuned)")

    @torch.no_grad()
    def track(self, measurements: torch.Tensor, batch_size: int = 512, intervals: torch.Tensor | None = None,
              return_cov: bool = False, r=None) -> TensorDict:
        """Whole sequences ``[B, T, 3]`` with the interval before each scan ``intervals [B, T]`` (s; None: ``self.dt``
        at every scan) -> ``state``, ``mode_probs``, ``member_probs [B, T, K]`` (K members, ``names``' order) and, with
        ``return_cov``, ``state_cov``; NaN before each track's first detection (``Tracker.track``'s arguments). Each
        member runs on the tracks it takes, as ``Tracker.track`` runs it alone. ``r``: refused (a bank's members are
        not told each track's r; ``from_names(r=...)`` gives them one)."""
        if r is not None:
            raise ValueError("a bank's members estimate each track's measurement std; to give them the radar's, build "
                             "the bank with r=METRES (NetworkBank.from_names, Tracker.pretrained('bank', r=...))")
        z = as_measurements(measurements, 3)
        if intervals is None:
            intervals = torch.full(z.shape[:2], self.dt, dtype=torch.float64)
        return by_segments(self, lambda zs, ivs, rows: self._track(zs, ivs, batch_size, return_cov, rows), z,
                           intervals, self.dt)

    def _track(self, z: torch.Tensor, intervals: torch.Tensor, batch_size: int, return_cov: bool,
               tracks: torch.Tensor | None = None) -> TensorDict:
        """``track``'s work on tracks that run from their first scan to their last without a restart (``tracks [B]``:
        their numbers in the caller's, where they are segments of its tracks)."""
        takes = self.takes(intervals)
        self.check(intervals, takes, tracks)
        if self.prune > 0:
            return self._track_by_scans(z, intervals, takes, return_cov)
        B, T, K = z.shape[0], z.shape[1], len(self.names)
        ran = takes.any(0).nonzero().flatten().tolist()  # the members that take a track: the others run on none
        state = torch.zeros(B, T, len(ran), 9, dtype=torch.float64)
        probs = torch.zeros(B, T, len(ran), N_MODES, dtype=torch.float64)
        cov = torch.zeros(B, T, len(ran), 9, 9, dtype=torch.float64) if return_cov else None
        loglik = torch.full((B, T, K), float("nan"), dtype=torch.float64)
        nets = list(self.members.values())
        for j, k in enumerate(ran):
            net = nets[k]
            rows = takes[:, k].nonzero().flatten()
            own = net.own_intervals(intervals[rows])  # as it runs alone (IMMNet.intervals_for)
            with torch.inference_mode():  # no autograd bookkeeping; its outputs are copied into the bank's below
                out, _ = run_network(net, z[rows], batch_size, own, return_cov, None, self.likelihood,
                                     self.max_position)
            state[rows, :, j] = out[keys.STATE].double()
            probs[rows, :, j] = out[keys.MODE_PROBS].double()
            loglik[rows, :, k] = out[keys.LOGLIK].double()
            if return_cov:
                cov[rows, :, j] = out[keys.STATE_COV].double()
        inc = self.temper * _weighed(loglik, takes[:, None, :])
        inc[:, 0] += self.log_prior  # summed in step's order, scan by scan from the prior: the same rounding
        log_w = inc.cumsum(1)
        out = _mix(log_w.masked_fill(~takes[:, None, :], float("-inf")), state, probs, cov, ran)
        waiting = before_first_detection(z)
        return TensorDict({k: blank_before_first_detection(v, waiting) for k, v in out.items()}, batch_size=[B, T])

    def _track_by_scans(self, z: torch.Tensor, intervals: torch.Tensor, takes: torch.Tensor, return_cov: bool
                        ) -> TensorDict:
        """``_track``'s outputs scan by scan (``step``, which gives ``track``'s numbers to the bit), so that a member
        pruned from a track (``prune``) runs on it no more; the streaming state is left as it was."""
        kept = vars(self).copy()  # the streaming state (``reset`` and ``step`` set new objects, never change these)
        try:
            self.reset(z.shape[0])
            self.log_w = self.log_w.masked_fill(~takes, float("-inf"))  # the whole track's members (``takes``)
            with torch.inference_mode():  # no autograd bookkeeping; the outputs are stacked into new tensors below
                outs = [self.step(z[:, t], dt=intervals[:, t]) for t in range(z.shape[1])]
        finally:
            vars(self).update(kept)
        return TensorDict({key: torch.stack([o[name] for o in outs], 1) for name, key in _STEP_OUTPUTS.items()
                           if return_cov or key != keys.STATE_COV}, batch_size=list(z.shape[:2]))

    # --- streaming: one scan at a time, as ``Tracker.step`` -----------------------------------------------------
    @property
    def dt(self) -> float:
        """The interval a scan given without one is taken at: the first member's ``dt``."""
        return float(next(iter(self.members.values())).dt)

    def _in_track(self, stays: torch.Tensor, alive: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(takes, shadow)``, each ``[B, K]`` bool, from ``stays`` (the member took every scan of the track so far)
        and ``alive`` (not pruned, not out): ``takes`` the members weighed into the track's estimate, ``shadow`` a
        member that ``defer``s on the track, run aside (not weighed in) so that it carries the track from the scan
        the members it defers to leave it (in ``track``, which sees the whole track, it does not run there)."""
        takes = stays & alive
        shadow = torch.zeros_like(takes)
        for k, others in self._defers.items():
            shadow[:, k] = takes[:, k] & stays[:, others].any(-1)
        return takes & ~shadow, shadow

    def _pruned(self, p: torch.Tensor, takes: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
        """``[B, K]`` bool: the members out of a track from the next scan on, with probabilities ``p [B, K]`` of the
        scan's mixture: below ``prune`` and not the most probable, on a track detected ``prune_after`` scans ago or
        more (``seen [B]`` scans since its first detection; none where ``prune`` is 0). A member that gives way
        (``defer``) is the bank's fallback and is never pruned: a track keeps the member that takes any scan."""
        if self.prune == 0:
            return torch.zeros_like(takes)
        pruned = takes & (p < self.prune) & (p < p.amax(-1, keepdim=True)) & (seen >= self.prune_after)[:, None]
        pruned[:, list(self._defers)] = False
        return pruned

    def _keeps_report(self, net: IMMNet) -> bool:
        """The member's report of the scan before is kept in its carry: the bank weighs what the member reports and
        the member corrects its output."""
        return self.likelihood is Likelihood.REPORTED and net.correct is not None

    def _fresh(self, net: IMMNet, n_tracks: int) -> TensorDict:
        """A member's carry for tracks that have not started: its own, with the report of the scan before
        (``("output", "state")``, zero) where it is kept (``_keeps_report``)."""
        carry = net.initial_carry(n_tracks)
        if self._keeps_report(net):
            carry.set(keys.OUTPUT, torch.zeros_like(carry.get(keys.FUSED)))
        return carry

    def _kept(self, net: IMMNet, after: TensorDict) -> TensorDict:
        """What a member keeps of a scan's output: its carry (and its report, as ``_fresh``)."""
        return after.select(*net.carry_keys, *((keys.OUTPUT,) if self._keeps_report(net) else ()))

    def reset(self, n_tracks: int) -> None:
        """``n_tracks`` (a whole number, at least 1) tracks that have not started, each member at its prior;
        ``n_gated`` back to 0."""
        n_tracks = check_n_tracks(n_tracks)
        self.carries = {name: self._fresh(net, n_tracks) for name, net in self.members.items()}
        self.log_w = self.log_prior.expand(n_tracks, -1).clone()
        fresh_tracks(self, n_tracks)
        self.stays = torch.ones(n_tracks, len(self.names), dtype=torch.bool)  # each member took every scan so far
        self.seen = torch.zeros(n_tracks, dtype=torch.long)  # scans since each one's first detection

    @torch.no_grad()
    def step(self, z: torch.Tensor, reset: torch.Tensor | None = None, dt=None) -> TensorDict:
        """One scan ``z [B, 3]`` (NaN: a missed detection) of every track (as many as the last ``reset``'s; the first
        scan without one sets their number), as ``Tracker.step``: ``reset [B]`` restarts
        those tracks (each member at its prior again), ``dt`` the time since each track's previous scan (a number or
        ``[B]``, s; None: ``self.dt``; a track's first scan after a reset takes it as nominal, ``track``'s scan 0).
        A member trained over a range coasts an interval longer than the range as ``track`` does (missed scans inside
        it, ``coast_scan``); a member drops out of a track at a scan it cannot take (its weight 0 until the track
        restarts); a scan no member still in the track can take is refused before anything changes. A track with no
        detection for longer than ``max_coast`` s restarts, as in ``Tracker.step`` (a long interval costs one scan). Returns
        ``("fused", "state")``, ``("fused", "cov")``, ``mode_probs`` and ``member_probs [B, K]``, NaN before a track's
        first detection. Over a sequence, ``track``'s numbers."""
        z = as_measurements(z, 2)
        B = z.shape[0]
        started = self.carries is not None
        gated, n_gated, reset, fresh, interval, since = begin_scan(self, z, reset, self.dt if dt is None else dt,
                                                                   self.dt, self.log_w.shape[0] if started else None)
        log_w = self.log_w.clone() if started else self.log_prior.expand(B, -1).clone()  # as after reset(B)
        if reset is not None:  # each member at its prior again
            log_w[reset] = self.log_prior
        # Tracker.step's check per track: each scan, as the member coasts a long interval (coast_cuts), inside its
        # range, or its one interval
        cut = [coast_cuts(net, interval, fresh) for net in self.members.values()]  # (scans, each's interval) per member
        fits = torch.stack([trained_for(net, each) for net, (_, each) in zip(self.members.values(), cut)], -1)
        stays = fits if not started else fits & (self.stays | fresh[:, None])  # every scan since the start
        takes, shadow = self._in_track(stays, log_w > -math.inf)
        lost = (~takes.any(-1)).nonzero().flatten()
        if len(lost):
            raise ValueError(f"no member of this bank still in track(s) {', '.join(str(int(i)) for i in lost[:5])} takes "
                             f"a scan after {float(interval[lost[0]]):g} s")
        if not started:
            self.reset(B)
        origin = next_origin(self.origin, gated, reset)  # the members' frame (one with a range guard keeps the radar's)
        self.n_gated += n_gated
        self.since, self.last, self.origin, self.stays = since, interval, origin, stays
        runs = takes | shadow
        K = len(self.names)
        state = torch.zeros(B, K, 9, dtype=torch.float64)
        probs = torch.zeros(B, K, N_MODES, dtype=torch.float64)
        cov = torch.zeros(B, K, 9, 9, dtype=torch.float64)
        loglik = torch.full((B, K), float("nan"), dtype=torch.float64)
        age = torch.zeros(B, dtype=torch.long)
        for k, (name, net) in enumerate(self.members.items()):
            carry = self.carries[name]
            if reset is not None:
                carry = select_rows(reset, self._fresh(net, B), carry)
            rows = runs[:, k].nonzero().flatten()
            every = len(rows) == B  # the whole batch: the carry as ``Tracker.step`` keeps it, not a copy of its rows
            if len(rows):
                at = torch.zeros_like(origin) if self._guarded[name] else origin.nan_to_num()
                z = to_local(gated, at)
                before, after = coast_scan(net, carry if every else carry[rows], z[rows], cut[k][0][rows],
                                           cut[k][1][rows], lambda td, net=net: self._kept(net, td))
                loglik[rows, k] = net.predictive_loglik(before, after, self.likelihood is Likelihood.REPORTED).double()
                state[rows, k] = to_world(net.estimate(after), at[rows])
                cov[rows, k] = net.reported_cov(after).double()
                probs[rows, k] = net.to_mode_probs(after.get(keys.EXPERT_PROBS)).double()
                age[rows] = torch.maximum(age[rows], after.get(keys.AGE))
                if every:
                    carry = self._kept(net, after)
                else:  # the carry with those rows replaced (one copy of each leaf)
                    carry = carry.apply(lambda old, new, rows=rows: old.index_copy(0, rows, new),
                                        self._kept(net, after))
            self.carries[name] = carry
        inc = _weighed(loglik, takes) + torch.where(shadow & torch.isfinite(loglik), loglik, 0.0)
        log_w = (log_w + self.temper * inc).masked_fill(~runs, float("-inf"))
        self.fresh = torch.zeros(B, dtype=torch.bool)
        ran = takes.any(0).nonzero().flatten().tolist()  # mixed over the members that take a track, as ``track``
        out = _mix(log_w.masked_fill(~takes, float("-inf")), state[:, ran], probs[:, ran], cov[:, ran], ran)
        seen = self.seen if reset is None else self.seen.masked_fill(reset, 0)
        self.seen = seen + (age > 0)
        self.log_w = log_w.masked_fill(self._pruned(out[keys.MEMBER_PROBS], takes, self.seen), float("-inf"))
        waiting = (age == 0)[:, None]  # no detection yet: no estimate
        return TensorDict({key: blank_before_first_detection(out[name].unsqueeze(1), waiting).squeeze(1)
                           for key, name in _STEP_OUTPUTS.items()}, batch_size=[B])


class BankMethod:
    """A bank of networks (``NetworkBank``) as a method of ``immnet evaluate`` and ``immnet track --method``:
    ``members`` shipped names or checkpoint paths, ``prior`` their prior probabilities, ``guard``, ``adapt`` and ``r``
    each member's (``load_network``'s; no range guard unless asked), ``likelihood`` and ``temper`` the bank's. Its
    output: ``state``, ``mode_probs`` and, with ``return_cov``, ``state_cov``. ``immnet evaluate`` scores a data set's
    window as one track, so the bank has no coasting limit here (``max_coast=math.inf``: a track coasts through any
    stretch without detections; ``immnet track`` sets its ``--max-coast``, the streaming and CSV APIs' limit)."""

    needs: tuple[str, ...] = ()

    build_options = {"return_cov": False, "guard": None}

    def __init__(self, members=DEFAULT_MEMBERS, prior=None, name: str = "immnet-bank", batch_size: int = 500,
                 guard=None, adapt=AS_CONFIGURED, r=AS_CONFIGURED, return_cov: bool = False, max_position: float = MAX_ABS_POSITION,
                 likelihood: str = LIKELIHOOD, temper: float = TEMPER, prune: float = PRUNE,
                 defer: dict | None = None, prune_after: int = PRUNE_AFTER, robust=AS_CONFIGURED):
        self.name = name
        self.net = NetworkBank.from_names(members, prior, guard, adapt, r, max_position=max_position,
                                          likelihood=likelihood, temper=temper, max_coast=math.inf, prune=prune,
                                          defer=defer, prune_after=prune_after, robust=robust)
        self.batch_size = batch_size
        self.return_cov = return_cov

    def check(self, batch: TensorDict) -> None:
        """A ValueError for tracks no member can take (``NetworkBank.check``)."""
        self.net.check(scan_intervals(batch))

    def track(self, batch: TensorDict) -> TensorDict:
        out = self.net.track(batch[keys.MEASUREMENTS], self.batch_size, scan_intervals(batch), self.return_cov)
        names = (keys.STATE, keys.MODE_PROBS, keys.STATE_COV) if self.return_cov else (keys.STATE, keys.MODE_PROBS)
        return TensorDict({k: out[k] for k in names}, batch_size=batch.batch_size)
