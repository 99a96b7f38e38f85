"""Where a tracker's error is, by flight phase: level, turn, climb/descent, speed change (real flights have no
mode labels; the phase is read from the truth's own velocity and acceleration).

At each scan, from the truth ``[lx, vx, ax, ly, vy, ay, lz, vz, az]``::

    turn rate        w = (vx ay - vy ax) / (vx^2 + vy^2)            |w| > TURN_DEG deg/s       -> turn
    vertical speed   vz                                               |vz| > CLIMB m/s           -> climb/descent
    along-track acc  a_t = (vx ax + vy ay) / sqrt(vx^2 + vy^2)        |a_t| > ACCEL m/s^2        -> speed change

A scan may be in several phases (a climbing turn); ``level`` is a scan in none. The RMSE of a phase pools the
squared position errors of its scored scans over all tracks (each scan counts once: a track's share is its
time in the phase).
"""

from __future__ import annotations

import math

import torch

from immnet.motion import POS

TURN_DEG = 0.5
CLIMB = 2.5
ACCEL = 0.3
PHASES = ("level", "turn", "climb/descent", "speed change")


def phases(truth: torch.Tensor) -> dict[str, torch.Tensor]:
    """Boolean masks ``[B, T]`` of each phase of ``PHASES`` from the truth ``[B, T, 9]`` (False where it is NaN)."""
    vx, ax, vy, ay, vz = truth[..., 1], truth[..., 2], truth[..., 4], truth[..., 5], truth[..., 7]
    speed2 = (vx * vx + vy * vy).clamp_min(1.0)
    w = (vx * ay - vy * ax) / speed2
    along = (vx * ax + vy * ay) / speed2.sqrt()
    known = torch.isfinite(truth).all(-1)
    turn = known & (w.abs() > math.radians(TURN_DEG))
    climb = known & (vz.abs() > CLIMB)
    accel = known & (along.abs() > ACCEL)
    return {"level": known & ~(turn | climb | accel), "turn": turn, "climb/descent": climb, "speed change": accel}


def rmse_by_phase(state: torch.Tensor, truth: torch.Tensor, scored: torch.Tensor) -> dict[str, dict]:
    """``{phase: {"rmse": pooled 3D-average position RMSE (m), "share": fraction of scored scans}}``."""
    pos = list(POS)
    se = (state[..., pos] - truth[..., pos]).to(torch.float64).square().mean(-1)  # the mean over the 3 axes
    out = {}
    n = int(scored.sum())
    for name, mask in phases(truth.to(torch.float64)).items():
        m = mask & scored
        k = int(m.sum())
        out[name] = {"rmse": float(se[m].mean().sqrt()) if k else None, "share": k / max(n, 1)}
    return out
