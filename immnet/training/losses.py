"""Training losses (docs/spec.md sections 4 and 6).

State loss: a weighted MSE, position 1, velocity 0.1, acceleration 0.02 (per component), each
trajectory weighted by ``1 / r`` (normalized to mean 1 over the batch) so low-noise trajectories
are not drowned by high-noise ones. Mode loss: the true cross-entropy ``-log mu_t[c_t]`` of the
expert probabilities summed per data mode (the paper's formula lacks the log), over the scans that have a label
(real flights have none, ``mode = -1``: they train on the state loss alone). Own-mode loss (stage 2,
optional): the state loss of each expert's own posterior on the scans of its own mode.
"""

from __future__ import annotations

import torch

from immnet.motion import ACC, POS, VEL


def component_weights(pos: float = 1.0, vel: float = 0.1, acc: float = 0.02) -> torch.Tensor:
    w = torch.zeros(9)
    w[list(POS)], w[list(VEL)], w[list(ACC)] = pos, vel, acc
    return w


def state_loss(est: torch.Tensor, truth: torch.Tensor, r: torch.Tensor | None, weights: torch.Tensor) -> torch.Tensor:
    """Weighted MSE of ``est`` against ``truth`` (``[B, T, ..., 9]``), trajectories weighted by ``1/r [B, ...]``."""
    se = (est - truth).square() * weights
    per_traj = se.sum(-1).mean(1)  # [B, ...]
    if r is None:
        return per_traj.mean()
    w = 1.0 / r.reshape(per_traj.shape)
    return (per_traj * w).sum() / w.sum()


def own_mode_loss(posts: torch.Tensor, truth: torch.Tensor, mode: torch.Tensor, expert_modes: torch.Tensor,
                  r: torch.Tensor | None, weights: torch.Tensor) -> torch.Tensor:
    """The state loss of each expert's posterior on the scans of the data mode it stands for.

    ``posts [B, T, M, 9]`` against ``truth [B, T, 9]``; ``mode [B, T]`` the true labels, ``expert_modes
    [M]`` each expert's mode. A weighted mean over the (trajectory, scan, expert) triples where the
    expert's mode is the true one (with one expert per mode: the true mode's expert, the "oracle pick"),
    each weighted by ``1/r`` of its trajectory. Zero where no expert stands for the scans' modes.
    """
    se = ((posts - truth.unsqueeze(-2)).square() * weights).sum(-1)  # [B, T, M]
    own = (mode.unsqueeze(-1) == expert_modes.to(mode.device)).to(se.dtype)
    if r is not None:
        own = own / r.reshape(-1, 1, 1)
    return (se * own).sum() / own.sum().clamp_min(torch.finfo(se.dtype).tiny)


def mode_loss(mode_probs: torch.Tensor, mode: torch.Tensor) -> torch.Tensor:
    """Cross-entropy ``-mean log mu[c]`` of data-mode probabilities ``[B, T, 4]`` against labels ``[B, T]``, over
    the labelled scans (``c >= 0``; real flights have none: ``-1``, and then the loss is 0)."""
    labelled = mode >= 0
    p = mode_probs.gather(-1, mode.clamp_min(0).unsqueeze(-1)).squeeze(-1)
    nll = -torch.log(p.clamp_min(1e-6))
    if bool(labelled.all()):
        return nll.mean()
    return (nll * labelled).sum() / labelled.sum().clamp_min(1)
