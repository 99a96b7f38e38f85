"""Position-error metrics of docs/evaluation.md, on whole tensors or accumulated batch by batch.

Notation: ``e[n, t, a] = x_hat[n, t, p_a] - x[n, t, p_a]`` the position error of trajectory ``n``
at step ``t`` on axis ``a`` (x, y, z; state indices ``POS = (0, 3, 6)``). A pair ``(n, t)`` is
scored when ``m[n, t]`` (:func:`scored_mask`): the truth is there (a finite row of ``states``; a
NaN row is no truth, e.g. padding after a track's end) and the track has started (``t`` at or
after trajectory ``n``'s first detection). With ``M_n = sum_t m[n,t]`` and ``N' `` the
trajectories with ``M_n > 0``. "avg" is always the mean of the three axis values.

- RMSE (the table):    ``RMSE_a = 1/N' sum_{n: M_n > 0} sqrt(1/M_n sum_t m e[n,t,a]^2)``
- pooled RMSE:         ``RMSE_a = sqrt(sum_{n,t} m e[n,t,a]^2 / sum_{n,t} m)``
- RMSE by interval:    the pooled RMSE of the scored pairs whose scan interval lies in each bin
  (:func:`rmse_by_interval`).
- RMSE over time:      ``RMSE_a(t) = sqrt(sum_n m e[n,t,a]^2 / sum_n m[n,t])`` (NaN where no pair is
  scored at ``t``); its "avg" curve is ``sqrt(1/3 sum_a RMSE_a(t)^2)``, on the table's scale.
- post-switch RMSE:    a switch of trajectory ``n`` is a step ``s >= 1`` with ``mode[n,s] !=
  mode[n,s-1]``, both labelled (``mode >= 0``; -1 is no label); its window is the scans ``t >= s``
  with ``tau[n,t] - tau[n,s] < 20 s`` (``POST_SWITCH_S``), ``tau`` the scan times (the cumulative sum
  of :func:`immnet.data.times.scan_intervals`; at 1 s scans the steps ``s, ..., s+19``, clipped to
  ``T-1``; without scan times the window is ``POST_SWITCH_STEPS`` scans). With ``S`` the scored pairs
  inside at least one window (each once),
  ``RMSE_a = sqrt(1/|S| sum_{(n,t) in S} e[n,t,a]^2)``. No such pair: ``None``.
- mode accuracy:       fraction of scored, labelled pairs with ``argmax_k mu[n,t,k] == mode[n,t]``;
  confusion ``C[i, j]`` counts those pairs with true mode ``i`` and predicted mode ``j``.

Without a mask every pair is scored (the formulas of a full data set). An estimate that is not
finite on a scored pair is not skipped: it makes the numbers NaN here, and
:class:`MetricAccumulator` reports the method as diverged instead of a number.
"""

from __future__ import annotations

import torch

from immnet.motion import N_MODES, POS

AXES = ("x", "y", "z")
POST_SWITCH_STEPS = 20
POST_SWITCH_S = 20.0
"""The post-switch window in seconds: ``POST_SWITCH_STEPS`` scans at 3D-LAST's 1 s."""


def position_error(state: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """``e = x_hat[..., POS] - x[..., POS]``, float64, ``[N, T, 3]`` from states ``[N, T, 9]``."""
    pos = list(POS)
    return state[..., pos].double() - truth[..., pos].double()


def scored_distance(err: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The 3-D distance ``|e|`` ``[N, T]`` of position errors ``err [N, T, 3]`` at the scored pairs ``mask``, 0 elsewhere
    (a track's worst error is its ``amax(1)``)."""
    return torch.linalg.vector_norm(err, dim=-1).where(mask, torch.zeros((), dtype=err.dtype))


def has_truth(truth: torch.Tensor) -> torch.Tensor:
    """Boolean ``[N, T]``: the true position is finite (a NaN row of ``states`` is no truth)."""
    return torch.isfinite(truth[..., list(POS)]).all(dim=-1)


def started(measurements: torch.Tensor) -> torch.Tensor:
    """Boolean ``[N, T]``: at or after the trajectory's first detection (a row without NaN)."""
    detected = ~torch.isnan(measurements).any(dim=-1)
    return torch.cummax(detected.to(torch.uint8), dim=-1).values.bool()


def scored_mask(truth: torch.Tensor, measurements: torch.Tensor | None = None) -> torch.Tensor:
    """Boolean ``[N, T]``: the pairs that are scored (truth there, and the track started if
    ``measurements`` are given). A property of the data: the same pairs for every method."""
    m = has_truth(truth)
    return m & started(measurements) if measurements is not None else m


def _mask(err: torch.Tensor, mask) -> torch.Tensor:
    return torch.ones(err.shape[:-1], dtype=torch.bool, device=err.device) if mask is None else mask.to(err.device)


def _sq(err: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``m e^2``: zero off the mask, NaN kept on it (a non-finite estimate is never hidden)."""
    return torch.where(mask.unsqueeze(-1), err.pow(2), torch.zeros((), dtype=err.dtype, device=err.device))


def _axes(values: torch.Tensor) -> dict[str, float]:
    """``{"x", "y", "z", "avg"}`` from a ``[3]`` tensor."""
    v = [float(x) for x in values]
    return {**dict(zip(AXES, v)), "avg": sum(v) / 3.0}


def per_trajectory_rmse(err: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """``sqrt(sum_t m e^2 / M_n)`` per trajectory and axis, ``[N, 3]`` (NaN where ``M_n = 0``)."""
    m = _mask(err, mask)
    return (_sq(err, m).sum(dim=-2) / m.sum(dim=-1, keepdim=True)).sqrt()


def rmse(err: torch.Tensor, mask: torch.Tensor | None = None) -> dict[str, float]:
    """The table's RMSE: per-trajectory RMSE over its scored steps, then the mean over the
    trajectories with at least one."""
    m = _mask(err, mask)
    return _axes(per_trajectory_rmse(err, m)[m.any(dim=-1)].mean(dim=0))


def rmse_pooled(err: torch.Tensor, mask: torch.Tensor | None = None) -> dict[str, float]:
    """``sqrt`` of the mean of ``e^2`` over all scored pairs, per axis."""
    m = _mask(err, mask)
    return _axes((_sq(err, m).sum(dim=(0, 1)) / m.sum()).sqrt())


def interval_bin(dt, edges) -> torch.Tensor:
    """The bin of each scan interval ``dt`` (s): ``i`` where ``edges[i] <= dt < edges[i+1]``, the last bin closed,
    and -1 outside the bins (NaN too); int64, ``dt``'s shape. A ValueError unless ``edges`` increase."""
    edges = [float(e) for e in edges]
    if len(edges) < 2 or any(b <= a for a, b in zip(edges, edges[1:])):
        raise ValueError(f"interval bin edges must be at least two increasing numbers, got {edges}")
    dt = torch.as_tensor(dt, dtype=torch.float64)
    e = torch.tensor(edges, dtype=torch.float64, device=dt.device)
    last = len(edges) - 2
    b = torch.bucketize(dt, e, right=True) - 1  # edges[b] <= dt < edges[b + 1]
    b = torch.where(dt == e[-1], last, b)
    return torch.where((b >= 0) & (b <= last), b, -1)


def rmse_by_interval(err: torch.Tensor, dt: torch.Tensor, edges, mask: torch.Tensor | None = None) -> list:
    """The pooled RMSE's "avg" (:func:`rmse_pooled`) of the scored pairs whose scan interval ``dt [N, T]`` (the time
    since the scan before) lies in each bin of :func:`interval_bin`; ``None`` for a bin without a scored pair. A bin
    holds a part of each track's scans, so the pairs are pooled, not averaged per track."""
    b = interval_bin(dt, edges).to(err.device)
    m = _mask(err, mask)
    bins = [m & (b == i) for i in range(len(edges) - 1)]
    return [rmse_pooled(err, sel)["avg"] if bool(sel.any()) else None for sel in bins]


def rmse_over_time(err: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """``sqrt(sum_n m e[n,t,a]^2 / sum_n m[n,t])``, ``[T, 3]``; see :func:`avg_curve`."""
    m = _mask(err, mask)
    return (_sq(err, m).sum(dim=0) / m.sum(dim=0).unsqueeze(-1)).sqrt()


def avg_curve(curve: torch.Tensor) -> torch.Tensor:
    """Per-axis-equivalent RMSE ``sqrt(mean_a RMSE_a(t)^2)`` from ``[..., 3]`` RMSEs."""
    return curve.pow(2).mean(dim=-1).sqrt()


def switch_steps(mode: torch.Tensor) -> torch.Tensor:
    """Boolean ``[N, T]``: True at ``s >= 1`` where ``mode[s] != mode[s-1]``, both labelled (>= 0)."""
    sw = torch.zeros(mode.shape, dtype=torch.bool, device=mode.device)
    sw[..., 1:] = (mode[..., 1:] != mode[..., :-1]) & (mode[..., 1:] >= 0) & (mode[..., :-1] >= 0)
    return sw


def post_switch_mask(mode: torch.Tensor, intervals: torch.Tensor | None = None) -> torch.Tensor:
    """Boolean ``[N, T]``: inside ``[s, s + POST_SWITCH_STEPS)`` for at least one switch ``s`` (clipped to T); with
    ``intervals [N, T]`` (s, :func:`immnet.data.times.scan_intervals`) the scans ``t >= s`` less than
    ``POST_SWITCH_S`` seconds after a switch ``s`` instead."""
    seconds = POST_SWITCH_S
    if intervals is None:  # every scan one step: the window in steps
        intervals, seconds = torch.ones(mode.shape, dtype=torch.float64, device=mode.device), POST_SWITCH_STEPS
    if intervals.shape != mode.shape:
        raise ValueError(f"intervals have shape {tuple(intervals.shape)}, expected the mode's {tuple(mode.shape)}")
    sw = switch_steps(mode)
    tau = intervals.to(torch.float64).cumsum(-1)  # any origin: only differences count
    # the latest switch at or before t is the nearest one: covered by some window iff by its window
    last = torch.where(sw, tau, torch.full_like(tau, -torch.inf)).cummax(dim=-1).values
    return (tau - last) < seconds


def post_switch_sums(err: torch.Tensor, mode: torch.Tensor, mask=None, intervals: torch.Tensor | None = None):
    """``(sum of e^2 over the scored pairs of the windows [3], number of them)``, for accumulation."""
    window = post_switch_mask(mode, intervals).to(err.device) & _mask(err, mask)
    return _sq(err, window).sum(dim=(0, 1)), int(window.sum())


def rmse_post_switch(err: torch.Tensor, mode: torch.Tensor, mask=None, intervals: torch.Tensor | None = None):
    """RMSE pooled over the ``POST_SWITCH_STEPS`` steps (with ``intervals``: the ``POST_SWITCH_S`` seconds) after
    every switch; ``None`` without any switch."""
    sq, count = post_switch_sums(err, mode, mask, intervals)
    return _axes((sq / count).sqrt()) if count else None


def confusion(mode_probs: torch.Tensor, mode: torch.Tensor, n_modes: int = N_MODES, mask=None) -> torch.Tensor:
    """``C[i, j]`` = number of scored, labelled steps with true mode ``i`` and ``argmax`` mode ``j``,
    int64 ``[K, K]``."""
    keep = mode >= 0
    if mask is not None:
        keep = keep & mask.to(keep.device)
    pred = mode_probs.argmax(dim=-1)[keep]
    true = mode[keep].to(torch.int64)
    return torch.bincount(true * n_modes + pred, minlength=n_modes * n_modes).reshape(n_modes, n_modes)


def mode_accuracy(mode_probs: torch.Tensor, mode: torch.Tensor, mask=None) -> float:
    """Fraction of scored, labelled steps whose most probable mode is the true one."""
    return _accuracy(confusion(mode_probs, mode, mode_probs.shape[-1], mask))


def _accuracy(c: torch.Tensor) -> float:
    """The share of a confusion matrix's counts on its diagonal (0 without any count)."""
    return float(c.diagonal().sum()) / max(int(c.sum()), 1)


class MetricAccumulator:
    """Every metric above, fed batch by batch (``update``) and read once (``compute``).

    Per-trajectory RMSEs are kept (``[N, 3]``, small); everything else is a running sum, so the
    result equals the whole-tensor functions whatever the batching. It also counts what is not
    scored (pairs without truth, pairs before a track's first detection, trajectories with no
    scored pair) and what failed: scored pairs whose estimate is not finite (``nan_scans``) and
    the trajectories holding them (``diverged``). A method with any such pair gets ``None``
    instead of its numbers: a failure is never averaged away.
    """

    def __init__(self):
        self.traj_rmse: list[torch.Tensor] = []
        self.traj_scored: list[torch.Tensor] = []
        self.sq_time = None  # sum_n m e^2, [T, 3]
        self.n_time = None  # sum_n m, [T]
        self.post_sq = torch.zeros(3, dtype=torch.float64)
        self.post_count = 0
        self.conf = None
        self.counts = dict.fromkeys(("scans", "without_truth", "before_first_detection", "nan_scans", "diverged"), 0)

    def update(self, state, truth, mode=None, mode_probs=None, measurements=None, intervals=None) -> None:
        """One batch: estimates ``state [B,T,9]`` against ``truth``; ``measurements`` (as the
        method saw them) mark the scans before each track's first detection, not scored; ``intervals
        [B,T]`` (s, :func:`immnet.data.times.scan_intervals`) make the post-switch window
        ``POST_SWITCH_S`` seconds (without them: ``POST_SWITCH_STEPS`` scans)."""
        err = position_error(state, truth).cpu()
        truth_ok = has_truth(truth).cpu()
        mask = scored_mask(truth, measurements).cpu()
        failed = mask & ~torch.isfinite(err).all(dim=-1)
        c = self.counts
        c["scans"] += mask.numel()
        c["without_truth"] += int((~truth_ok).sum())
        c["before_first_detection"] += int((truth_ok & ~mask).sum())
        c["nan_scans"] += int(failed.sum())
        c["diverged"] += int(failed.any(dim=-1).sum())
        self.traj_rmse.append(per_trajectory_rmse(err, mask))
        self.traj_scored.append(mask.any(dim=-1))
        sq, cnt = _sq(err, mask).sum(dim=0), mask.sum(dim=0)
        self.sq_time = sq if self.sq_time is None else self.sq_time + sq
        self.n_time = cnt if self.n_time is None else self.n_time + cnt
        if mode is not None:
            mode = mode.cpu()
            iv = None if intervals is None else intervals.cpu()
            s, k = post_switch_sums(err, mode, mask, iv)
            self.post_sq += s
            self.post_count += k
            if mode_probs is not None:
                k = confusion(mode_probs.cpu(), mode, mask=mask)
                self.conf = k if self.conf is None else self.conf + k

    def compute(self) -> dict:
        """``rmse``, ``rmse_pooled``, ``rmse_post_switch`` (dicts, or None: no switch, or diverged),
        ``rmse_over_time`` ``[T, 3]``, ``per_trajectory`` ``[N, 3]`` (NaN: nothing scored, or
        diverged), ``mode_accuracy`` and ``confusion`` (or None), and ``counts``: ``scans``,
        ``without_truth``, ``before_first_detection``, ``scored``, ``trajectories``, ``excluded``
        (trajectories with no scored pair), ``nan_scans`` and ``diverged``."""
        if not self.traj_rmse:
            raise ValueError("no trajectories were evaluated")
        traj, scored = torch.cat(self.traj_rmse), torch.cat(self.traj_scored)
        counts = dict(self.counts, scored=int(self.n_time.sum()), trajectories=int(scored.numel()),
                      excluded=int((~scored).sum()))
        if not scored.any():
            raise ValueError("no trajectory has a scan with both truth and a detection to score")
        ok = counts["diverged"] == 0
        labelled = self.conf is not None and ok and int(self.conf.sum()) > 0  # real flights have no mode labels
        return {
            "rmse": _axes(traj[scored].mean(dim=0)) if ok else None,
            "rmse_pooled": _axes((self.sq_time.sum(dim=0) / counts["scored"]).sqrt()) if ok else None,
            "rmse_post_switch": _axes((self.post_sq / self.post_count).sqrt()) if ok and self.post_count else None,
            "rmse_over_time": (self.sq_time / self.n_time.unsqueeze(-1)).sqrt(),
            "per_trajectory": traj,
            "mode_accuracy": _accuracy(self.conf) if labelled else None,
            "confusion": self.conf if labelled else None,
            "counts": counts,
        }
