"""Training losses (SPEC.md sections 4 and 6).

State loss: a weighted MSE, position 1, velocity 0.1, acceleration 0.02 (per component), each
trajectory weighted by ``1 / r`` (normalized to mean 1 over the batch) so low-noise trajectories
are not drowned by high-noise ones. Mode loss: the true cross-entropy ``-log mu_t[c_t]`` of the
expert probabilities summed per data mode (the paper's formula lacks the log).
"""

from __future__ import annotations

import torch

from immnet.motion import ACC, POS, VEL


def component_weights(pos: float = 1.0, vel: float = 0.1, acc: float = 0.02, device=None) -> torch.Tensor:
    w = torch.zeros(9, device=device)
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


def mode_loss(mode_probs: torch.Tensor, mode: torch.Tensor) -> torch.Tensor:
    """Cross-entropy ``-mean log mu[c]`` of data-mode probabilities ``[B, T, 4]`` against labels ``[B, T]``."""
    p = mode_probs.gather(-1, mode.unsqueeze(-1)).squeeze(-1)
    return -torch.log(p.clamp_min(1e-6)).mean()
