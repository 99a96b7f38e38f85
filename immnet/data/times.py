"""Scan times: the one reading of when each scan of a batch was made (docs/data.md, "Scan times").

A batch carries a nominal interval ``dt [B]`` and, where scans are not on a grid of ``dt``, the time
of each scan ``t [B, T]`` (seconds, strictly increasing along ``T``; any origin, epoch times included).
Every tracker reads the interval before each scan, :func:`scan_intervals`; scan 0 has no interval
before it (a track starts there) and gets the nominal ``dt``.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

from immnet import keys


SNAP = 1e-6
"""Relative distance below which a scan interval is read as the nominal ``dt`` (:func:`scan_intervals`):
above float32's rounding of ``dt`` (6e-8) and the rounding of ``k dt`` in float64, far below any timing
a sensor reports (5 microseconds at 5 s)."""


def nominal_dt(batch: TensorDict, dtype=torch.float64, device=None) -> torch.Tensor:
    """The nominal interval per track ``[B]``: ``dt`` where the batch carries it, else the median spacing of
    ``t``, else 1 s."""
    B = batch.batch_size[0]
    if keys.DT in batch.keys():
        return torch.as_tensor(batch[keys.DT], dtype=dtype, device=device).reshape(-1).expand(B)
    if keys.TIME in batch.keys() and batch[keys.TIME].shape[-1] > 1:
        t = torch.as_tensor(batch[keys.TIME], dtype=torch.float64, device=device)
        return t.diff(dim=-1).median(-1).values.to(dtype)
    return torch.ones(B, dtype=dtype, device=device)


def scan_intervals(batch: TensorDict, dtype=torch.float64, device=None) -> torch.Tensor:
    """The interval before each scan ``[B, T]`` (s): the differences of ``t`` where the batch carries it,
    else ``dt`` at every scan; at scan 0 the nominal ``dt`` (:func:`nominal_dt`). A difference within
    ``SNAP`` (relative) of the nominal ``dt`` is that ``dt``: scans at ``k dt`` read exactly as without ``t``.

    Differences are taken in float64 before any cast, so that epoch times (1.7e9 s) keep their
    hundredths of a second."""
    T = batch[keys.MEASUREMENTS].shape[1]
    first = nominal_dt(batch, torch.float64, device)
    if keys.TIME not in batch.keys():
        return first[:, None].expand(-1, T).to(dtype)
    t = torch.as_tensor(batch[keys.TIME], dtype=torch.float64, device=device)
    step = t.diff(dim=-1)
    nominal = first[:, None]
    # k dt rounds (0.1 s: differences 0.1 +- 6e-15; a dt stored float32 differs from the float64 times by
    # ~1e-8 dt): an interval within SNAP of the nominal one is the nominal one, so that scans at k dt read
    # exactly as the same data without t
    step = torch.where((step - nominal).abs() <= SNAP * nominal, nominal, step)
    return torch.cat([nominal, step], -1).to(dtype)


def regular(intervals: torch.Tensor) -> bool:
    """True where every track's every interval after scan 0 is one value (the fixed-interval fast paths)."""
    rest = intervals[:, 1:]
    return rest.numel() == 0 or bool((rest == rest.reshape(-1)[0]).all())
