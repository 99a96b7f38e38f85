"""Position-error metrics of SPEC.md section 5, on whole tensors or accumulated batch by batch.

Notation: ``e[n, t, a] = x_hat[n, t, p_a] - x[n, t, p_a]`` the position error of trajectory ``n``
at step ``t`` on axis ``a`` (x, y, z; state indices ``POS = (0, 3, 6)``). Every step
``t = 0..T-1`` counts. "avg" is always the mean of the three axis values.

- RMSE (the table):    ``RMSE_a = 1/N sum_n sqrt(1/T sum_t e[n,t,a]^2)``
- pooled RMSE:         ``RMSE_a = sqrt(1/(N T) sum_n sum_t e[n,t,a]^2)``
- RMSE over time:      ``RMSE_a(t) = sqrt(1/N sum_n e[n,t,a]^2)``; its "avg" curve is the
  per-axis-equivalent ``sqrt(1/3 sum_a RMSE_a(t)^2)``, on the same scale as the table.
- post-switch RMSE:    a switch of trajectory ``n`` is a step ``s >= 1`` with
  ``mode[n,s] != mode[n,s-1]``; its window is ``s, s+1, ..., s+19`` clipped to ``T-1``. With
  ``S`` the set of pairs ``(n, t)`` inside at least one window (each pair once, even where
  windows overlap), ``RMSE_a = sqrt(1/|S| sum_{(n,t) in S} e[n,t,a]^2)``: pooled over all
  trajectories and steps in the windows. No switch anywhere: ``None``.
- mode accuracy:       fraction of pairs ``(n, t)`` with ``argmax_k mu[n,t,k] == mode[n,t]``;
  confusion ``C[i, j]`` counts pairs with true mode ``i`` and predicted mode ``j``.
"""

from __future__ import annotations

import torch

from immnet.motion import POS

AXES = ("x", "y", "z")
POST_SWITCH_STEPS = 20
N_MODES = 4


def position_error(state: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """``e = x_hat[..., POS] - x[..., POS]``, float64, ``[N, T, 3]`` from states ``[N, T, 9]``."""
    pos = list(POS)
    return state[..., pos].double() - truth[..., pos].double()


def _axes(values: torch.Tensor) -> dict[str, float]:
    """``{"x", "y", "z", "avg"}`` from a ``[3]`` tensor."""
    v = [float(x) for x in values]
    return {**dict(zip(AXES, v)), "avg": sum(v) / 3.0}


def per_trajectory_rmse(err: torch.Tensor) -> torch.Tensor:
    """``sqrt(mean_t e^2)`` per trajectory and axis, ``[N, 3]``."""
    return err.pow(2).mean(dim=-2).sqrt()


def rmse(err: torch.Tensor) -> dict[str, float]:
    """The table's RMSE: per-trajectory RMSE over time, then the mean over trajectories."""
    return _axes(per_trajectory_rmse(err).mean(dim=0))


def rmse_pooled(err: torch.Tensor) -> dict[str, float]:
    """``sqrt`` of the mean of ``e^2`` over all trajectories and steps, per axis."""
    return _axes(err.pow(2).mean(dim=(0, 1)).sqrt())


def rmse_over_time(err: torch.Tensor) -> torch.Tensor:
    """``sqrt(mean_n e[n,t,a]^2)``, ``[T, 3]``; see :func:`avg_curve` for the one-line summary."""
    return err.pow(2).mean(dim=0).sqrt()


def avg_curve(curve: torch.Tensor) -> torch.Tensor:
    """Per-axis-equivalent RMSE ``sqrt(mean_a RMSE_a(t)^2)`` from ``[..., 3]`` RMSEs."""
    return curve.pow(2).mean(dim=-1).sqrt()


def switch_steps(mode: torch.Tensor) -> torch.Tensor:
    """Boolean ``[N, T]``: True at ``s >= 1`` where ``mode[s] != mode[s-1]``."""
    sw = torch.zeros(mode.shape, dtype=torch.bool, device=mode.device)
    sw[..., 1:] = mode[..., 1:] != mode[..., :-1]
    return sw


def post_switch_mask(mode: torch.Tensor, steps: int = POST_SWITCH_STEPS) -> torch.Tensor:
    """Boolean ``[N, T]``: inside ``[s, s + steps)`` for at least one switch ``s`` (clipped to T)."""
    sw = switch_steps(mode).to(torch.int64)
    # a step t is covered when a switch lies in (t - steps, t]: a running sum over the last `steps`.
    c = torch.cumsum(sw, dim=-1)
    lagged = torch.zeros_like(c)
    lagged[..., steps:] = c[..., :-steps]
    return (c - lagged) > 0


def post_switch_sums(err: torch.Tensor, mode: torch.Tensor, steps: int = POST_SWITCH_STEPS):
    """``(sum of e^2 over the windows [3], number of (n, t) pairs in them)``, for accumulation."""
    mask = post_switch_mask(mode, steps)
    return (err.pow(2) * mask.unsqueeze(-1)).sum(dim=(0, 1)), int(mask.sum())


def rmse_post_switch(err: torch.Tensor, mode: torch.Tensor, steps: int = POST_SWITCH_STEPS):
    """RMSE pooled over the ``steps`` steps after every switch; ``None`` without any switch."""
    sq, count = post_switch_sums(err, mode, steps)
    return _axes((sq / count).sqrt()) if count else None


def confusion(mode_probs: torch.Tensor, mode: torch.Tensor, n_modes: int = N_MODES) -> torch.Tensor:
    """``C[i, j]`` = number of steps with true mode ``i`` and ``argmax`` mode ``j``, int64 ``[K, K]``."""
    pred = mode_probs.argmax(dim=-1).reshape(-1)
    true = mode.reshape(-1).to(torch.int64)
    return torch.bincount(true * n_modes + pred, minlength=n_modes * n_modes).reshape(n_modes, n_modes)


def mode_accuracy(mode_probs: torch.Tensor, mode: torch.Tensor) -> float:
    """Fraction of steps whose most probable mode is the true one."""
    c = confusion(mode_probs, mode, mode_probs.shape[-1])
    return float(c.diagonal().sum()) / max(int(c.sum()), 1)


class MetricAccumulator:
    """Every metric above, fed batch by batch (``update``) and read once (``compute``).

    Per-trajectory RMSEs are kept (``[N, 3]``, small); everything else is a running sum, so the
    result equals the whole-tensor functions whatever the batching.
    """

    def __init__(self, steps: int = POST_SWITCH_STEPS, n_modes: int = N_MODES):
        self.steps, self.n_modes = steps, n_modes
        self.traj_rmse: list[torch.Tensor] = []
        self.sq_time = None  # sum_n e^2, [T, 3]
        self.n = 0
        self.post_sq = torch.zeros(3, dtype=torch.float64)
        self.post_count = 0
        self.conf = None

    def update(self, state, truth, mode=None, mode_probs=None) -> None:
        err = position_error(state, truth).cpu()
        self.traj_rmse.append(per_trajectory_rmse(err))
        sq = err.pow(2).sum(dim=0)
        self.sq_time = sq if self.sq_time is None else self.sq_time + sq
        self.n += err.shape[0]
        if mode is not None:
            mode = mode.cpu()
            s, c = post_switch_sums(err, mode, self.steps)
            self.post_sq += s
            self.post_count += c
            if mode_probs is not None:
                c = confusion(mode_probs.cpu(), mode, self.n_modes)
                self.conf = c if self.conf is None else self.conf + c

    def compute(self) -> dict:
        """``rmse``, ``rmse_pooled``, ``rmse_post_switch`` (dicts or None), ``rmse_over_time``
        ``[T, 3]``, ``per_trajectory`` ``[N, 3]``, ``mode_accuracy`` and ``confusion`` (or None)."""
        if not self.n:
            raise ValueError("no trajectories were evaluated")
        traj = torch.cat(self.traj_rmse)
        mse_t = self.sq_time / self.n
        out = {
            "rmse": _axes(traj.mean(dim=0)),
            "rmse_pooled": _axes(mse_t.mean(dim=0).sqrt()),
            "rmse_post_switch": _axes((self.post_sq / self.post_count).sqrt()) if self.post_count else None,
            "rmse_over_time": mse_t.sqrt(),
            "per_trajectory": traj,
            "mode_accuracy": None,
            "confusion": None,
        }
        if self.conf is not None:
            out["confusion"] = self.conf
            out["mode_accuracy"] = float(self.conf.diagonal().sum()) / max(int(self.conf.sum()), 1)
        return out
