"""The decoupled IMM: one IMM per Cartesian axis, each with modes of its own (docs/baselines.md).

A real aircraft climbs while it flies level in the plane, or speeds up while it holds its altitude: one
mode for the whole 9-D state makes the vertical filter switch with the horizontal one. The decoupled IMM
runs three independent IMMs over the per-axis states ``[l, v, a]``, each measuring its own coordinate::

    x^a = [l_a, v_a, a_a]     z^a_t = H x^a_t + v,  H = [1, 0, 0],  v ~ N(0, r^2)
    F^a_j, Q^a_j              the axis-a block of model j's F_j, Q_j (block diagonal for CV and CA)

with the interaction, mode-matched filters, mode update and combination of ``immnet.imm.runner.run``, the
one core, over ``3 B`` tracks of one coordinate each. For an isotropic ``r`` the three measurement
coordinates are independent, so this is exact per axis. Models whose transition couples the axes (the
coordinated turn) have no per-axis form and are refused.
"""

from __future__ import annotations

from typing import Sequence

import torch
from tensordict import TensorDict

from immnet import keys
from immnet.filters.base import interval_or_intervals, output
from immnet.filters.imm import first_detection, initial_state
from immnet.filters.trackers import ISOTROPIC, _linear_network, _ModelSetIMM, variance
from immnet.imm.runner import linear_transition, run
from immnet.motion import AXES, AXIS_OF, Modes, coupling
from immnet.motion.models import axis_blocks, axis_states, block_diagonal


class PerAxisIMMTracker(_ModelSetIMM):
    """Three independent IMMs, one per axis, over a model set of axis-separable models (CV, CA).

    ``r``: the assumed measurement std (m), or ``"data"`` (each track's own ``r``); ``sigma_q`` one for all
    models or one per model; ``p_stay``: the Markov chain's staying probability (or a matrix ``[M, M]``).
    ``track`` gives ``state [B, T, 9]`` and ``("mode", "probs") [B, T, 3, M]``, each axis's mode
    probabilities (no data modes: an axis has none of 3D-LAST's). ``robust``: Huber's ``k`` of each axis's update
    (``immnet.imm.kalman``'s module doc; the distance is the axis's own innovation over its standard deviation),
    None: off.
    """

    def __init__(self, model_set, r: float | str, sigma_q: float | Sequence[float], p_stay=0.98,
                 dtype="float64", name: str = "imm-axis", return_cov: bool = False, robust: float | None = None):
        super().__init__(model_set, r, sigma_q, p_stay, dtype, name, return_cov, robust, ISOTROPIC)
        moving = coupling(self.model_set, AXIS_OF)
        if moving:
            raise ValueError(f"a per-axis IMM needs models whose F is block diagonal per axis; {moving} couple the axes")

    def network(self, dt: float = 1.0):
        """This IMM as IMMNet with nothing learned and modes per axis (``IMMNet(modes="axis")``; otherwise as
        ``IMMTracker.network``): each axis's mix, mode update and fusion over the model set's filter experts, whose
        9-D filters are the three axes' filters side by side. It filters what ``track`` filters, to float64
        rounding, each track from its first detection on; ``robust``: the experts' Huber update per axis (each axis's
        weight from its own innovation, ``FilterGain(robust=k)`` with modes per group). A ValueError for a full
        transition matrix."""
        return _linear_network(self.name, self.model_set, self.sigma_q, self.r, self._p_stay, dt, self.dtype,
                               modes=Modes.AXIS, robust=self.robust)

    def track(self, batch: TensorDict) -> TensorDict:
        self.check(batch)
        z = batch[keys.MEASUREMENTS].to(self.dtype)
        B, T, _ = z.shape
        dev = z.device
        M = len(self.model_set)
        dt = interval_or_intervals(batch, self.dtype, dev)
        F = self.model_set.F(dt, dtype=self.dtype, device=dev)  # [M | B, T, M, 9, 9]
        Q = self.model_set.Q(self.sigma_q, dt, dtype=self.dtype, device=dev)
        r = self.measurement.std(batch, self.dtype, dev)
        x0, P0 = initial_state(z, r)

        def per_track(blocks: torch.Tensor, shared: bool = False) -> torch.Tensor:
            """Axis blocks ``[3, B, ...]`` (or, ``shared``, ``[3, ...]``, one for every track) -> ``[3 B, ...]``,
            axis-major."""
            if shared:
                blocks = blocks[:, None].expand(AXES, B, *blocks.shape[1:])
            return blocks.reshape(AXES * B, *blocks.shape[2:])

        x = per_track(axis_states(x0))[:, None].expand(AXES * B, M, 3).contiguous()
        P = per_track(axis_blocks(P0))[:, None].expand(AXES * B, M, 3, 3).contiguous()
        mu = torch.full((AXES * B, M), 1.0 / M, dtype=self.dtype, device=dev)
        R = variance(r, self.dtype, dev)
        R = R.repeat(AXES) if R.dim() == 1 else R
        za = z.permute(2, 0, 1).reshape(AXES * B, T, 1)
        H = torch.tensor([[1.0, 0.0, 0.0]], dtype=self.dtype, device=dev)
        transition = linear_transition(per_track(axis_blocks(F), F.dim() == 3), per_track(axis_blocks(Q), Q.dim() == 3))
        states, probs, _, *cov = run(za, x, P, mu, self.Pi.to(dtype=self.dtype, device=dev), transition, R, H=H,
                                     return_cov=self.return_cov, start=first_detection(z).repeat(AXES), robust=self.robust)
        state = states.reshape(AXES, B, T, 3).permute(1, 2, 0, 3).reshape(B, T, 9)
        probs = probs.reshape(AXES, B, T, M).permute(1, 2, 0, 3)
        extra = {keys.EXPERT_PROBS: probs}
        if cov:  # the axes' 3x3 blocks on the diagonal of the 9-D covariance (the axes are independent)
            extra[keys.STATE_COV] = block_diagonal(cov[0].reshape(AXES, B, T, 3, 3))
        return output(state, extra, measurements=z)
