"""Measurements checked at the edge: what a sensor cannot report is a missed detection, counted.

A radar reports a finite position within its reach. A measurement row with a non-finite component
(``inf``, ``-inf``; a partly NaN row) or a component beyond ``limit`` metres from the radar
(``|z_a| > limit``, default :data:`MAX_ABS_POSITION`) is not a detection: it is replaced by a missed
detection (a NaN row) before any tracker sees it, and counted, so that the caller can report it.
A row that is all NaN already is a missed detection and is not counted.
"""

from __future__ import annotations

import numpy as np

MAX_ABS_POSITION = 1e7
"""Default limit on ``|z_a|`` in metres (10,000 km: beyond any radar's reach, far inside float32)."""


def check_limit(limit: float) -> float:
    """``limit`` as a float; a ValueError unless it is positive (``inf`` switches the check off)."""
    limit = float(limit)
    if not limit > 0:  # also NaN
        raise ValueError(f"the measurement limit must be a positive number of metres, got {limit:g}")
    return limit


def gate_measurements(z, limit: float = MAX_ABS_POSITION):
    """``(z_gated, n_gated)``: ``z [..., 3]`` (torch or numpy) with every row that a sensor cannot
    report (a non-finite component, or ``|z_a| > limit``) set to NaN, and how many such rows there
    were (rows that were all NaN before are missed detections already and are not counted).

    The input is not modified; the output has the input's type, dtype and device.
    """
    import torch

    limit = check_limit(limit)
    xp = np if isinstance(z, np.ndarray) else torch
    z = z if xp is np else torch.as_tensor(z)
    if z.shape[-1:] != (3,):
        raise ValueError(f"measurements must be [..., 3], got shape {tuple(z.shape)}")
    bad = ~(xp.isfinite(z) & (abs(z) <= limit)).all(-1) & ~xp.isnan(z).all(-1)
    out = z.copy() if xp is np else z.clone()
    out[bad] = float("nan")
    return out, int(bad.sum())
