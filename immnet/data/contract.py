"""What a data set's arrays must hold: dtypes, shapes, finiteness and ranges (docs/data.md).

``check_arrays(arrays, where)`` is the one check of a data set's contents, for an ``.npz``
interchange file and a data set directory alike; it raises a one-line ValueError naming the array,
what is wrong and, for a value, where (``[n, t]``). ``N`` trajectories of ``T`` scans:

- ``measurements [N, T, 3]`` float32/float64, ``N >= 1``, ``T >= 1``; any value (a NaN row is a
  missed detection; a measurement no sensor could report is gated where data enters a tracker,
  :func:`immnet.data.validate.gate_measurements`).
- ``states [N, T, 9]`` float32/float64: each row all finite, or all NaN (no truth at that scan:
  the padding of a track that ended before ``T``, or began after 0).
- ``mode [N, T]`` integer: 0 CV, 1 CA, 2 CT+, 3 CT-, or :data:`NO_LABEL` (-1, no label at that scan).
- ``turn_rate [N, T]`` float32/float64 (rad/s): finite, or NaN where unknown.
- ``r [N]`` (m) and ``dt`` (s): finite and > 0; integers accepted for these two.
- ``t [N, T]`` (s, optional): scan times, finite and strictly increasing along ``T`` (any origin, epoch
  times included; float64 keeps their hundredths of a second); integers accepted. Absent: scan ``k``
  is at ``k dt``.
- ``meas_cov [N, T, 3, 3]`` float32/float64 (m^2, optional): each detection's measurement covariance, a matrix all
  finite with a positive diagonal, or all NaN (a missed detection, or padding).

float16 is refused: its 11-bit significand would round positions of tens of km to 16-32 m, more
than the measurement noise. Values are checked ``ROWS`` trajectories at a time, so that a
memory-mapped set is read once with bounded memory.
"""

from __future__ import annotations

import numpy as np

from immnet import keys
from immnet.motion import MODE_NAMES, N_MODES

NO_LABEL = -1
"""A ``mode`` value meaning "no label at this scan" (e.g. padding after a track's end)."""
ROWS = 1024
FLOATS = (np.dtype(np.float32), np.dtype(np.float64))
TRAIL = {keys.MEASUREMENTS: ("T", 3), keys.STATES: ("T", 9), keys.MODE: ("T",), keys.TURN_RATE: ("T",),
         keys.R: (), keys.TIME: ("T",), keys.MEAS_COV: ("T", 3, 3)}
"""Trailing shapes after ``[N]`` (``T`` filled in): the contract of a data set's arrays."""
_INT_OK = (keys.R, keys.DT, keys.MODE, keys.TIME)


def trailing_shape(key: str, T: int) -> tuple[int, ...]:
    """Array ``key``'s shape after ``[N]`` in a set of ``T`` scans (``TRAIL``'s, ``()`` for ``dt``)."""
    return tuple(T if d == "T" else d for d in TRAIL.get(key, ()))


def check_dtype(key: str, dtype, where: str) -> None:
    """A ValueError unless ``dtype`` suits array ``key`` (see the module docstring)."""
    dtype = np.dtype(dtype)
    if key == keys.MODE:
        if dtype.kind not in "iu":
            raise ValueError(f"{where}: array 'mode' must be integer (0..3, {NO_LABEL} = no label), got {dtype}")
        return
    if dtype == np.float16:
        raise ValueError(f"{where}: array {key!r} is float16, which rounds positions of tens of km to 16-32 m; "
                         f"store float32 or float64")
    if dtype in FLOATS or (key in _INT_OK and dtype.kind in "iu"):
        return
    raise ValueError(f"{where}: array {key!r} must be float32 or float64, got {dtype}")


def check_shapes(shapes: dict[str, tuple], where: str) -> tuple[int, int]:
    """``(N, T)`` from ``measurements``; a ValueError for any array of another shape or an empty set."""
    if keys.MEASUREMENTS not in shapes:
        raise ValueError(f"{where}: the required array 'measurements' [N,T,3] is missing (has {sorted(shapes)})")
    shape = tuple(shapes[keys.MEASUREMENTS])
    if len(shape) != 3 or shape[2] != 3:
        raise ValueError(f"{where}: array 'measurements' has shape {shape}, expected [N,T,3]")
    n, T = shape[:2]
    if n < 1 or T < 1:
        raise ValueError(f"{where}: array 'measurements' has shape {shape}: a data set needs N >= 1 trajectories "
                         f"of T >= 1 scans")
    for key in TRAIL:
        if key in shapes:
            want = (n, *trailing_shape(key, T))
            if tuple(shapes[key]) != want:
                raise ValueError(f"{where}: array {key!r} has shape {tuple(shapes[key])}, expected {want}")
    return n, T


def _first(bad: np.ndarray, row0: int) -> str:
    """``[n, t]`` (or ``[n]``) of the first True of ``bad``, ``n`` counted from ``row0``."""
    idx = np.argwhere(bad)[0]
    return "[" + ", ".join(str(int(i) + (row0 if j == 0 else 0)) for j, i in enumerate(idx)) + "]"


def check_values(key: str, a: np.ndarray, where: str, row0: int = 0) -> None:
    """A ValueError at the first value of ``a`` (rows ``row0..`` of array ``key``) out of its range."""
    if key == keys.STATES:
        if np.isfinite(a.sum()):  # a finite sum: every value is finite (one fast pass over the rows)
            return
        bad = ~(np.isnan(a).all(-1) | np.isfinite(a).all(-1))
        if bad.any():
            raise ValueError(f"{where}: array 'states' at {_first(bad, row0)} is neither all finite nor all NaN "
                             f"(a scan without truth is a row of NaN)")
    elif key == keys.MODE:
        bad = (a < NO_LABEL) | (a >= N_MODES)
        if bad.any():
            at = _first(bad, row0)
            raise ValueError(f"{where}: array 'mode' holds {int(a[bad][0])} at {at}; valid: 0..{N_MODES - 1} "
                             f"({', '.join(MODE_NAMES)}) or {NO_LABEL} (no label)")
    elif key == keys.TURN_RATE:
        bad = np.isinf(a)
        if bad.any():
            raise ValueError(f"{where}: array 'turn_rate' at {_first(bad, row0)} is {a[bad][0]} (finite or NaN only)")
    elif key == keys.TIME:
        bad = ~np.isfinite(a)
        if bad.any():
            raise ValueError(f"{where}: array 't' at {_first(bad, row0)} is {a[bad][0]}; scan times must be finite (s)")
        if a.shape[-1] > 1:
            step = np.diff(a.astype(np.float64), axis=-1)
            bad = np.concatenate([np.zeros_like(step[..., :1], dtype=bool), step <= 0], -1)
            if bad.any():
                n, k = np.argwhere(bad)[0]
                raise ValueError(f"{where}: array 't' is not strictly increasing at {_first(bad, row0)}: scan time "
                                 f"{float(a[n, k])!r} s follows {float(a[n, k - 1])!r} s (scan times must increase along T)")
    elif key == keys.MEAS_COV:
        flat = a.reshape(*a.shape[:-2], 9)
        diag = a[..., [0, 1, 2], [0, 1, 2]]
        bad = ~(np.isnan(flat).all(-1) | (np.isfinite(flat).all(-1) & (diag > 0).all(-1)))
        if bad.any():
            raise ValueError(f"{where}: array 'meas_cov' at {_first(bad, row0)} is neither a covariance (all finite, "
                             f"a positive diagonal) nor all NaN (a missed detection)")
    elif key in (keys.R, keys.DT):
        bad = ~(np.isfinite(a) & (a > 0))
        if bad.any():
            at = f" at {_first(bad, row0)}" if a.ndim else ""
            unit = "m" if key == keys.R else "s"
            raise ValueError(f"{where}: array {key!r}{at} is {a[bad][0]:g}; it must be finite and > 0 ({unit})")


def check_arrays(arrays: dict, where: str) -> tuple[int, int]:
    """Check every array of ``arrays`` (numpy or memory-mapped; ``dt`` a scalar or ``[N]``); ``(N, T)``."""
    arrays = {k: v for k, v in arrays.items() if k in TRAIL or k == keys.DT}
    for key, a in arrays.items():
        check_dtype(key, a.dtype, where)
    n, T = check_shapes({k: tuple(a.shape) for k, a in arrays.items() if k != keys.DT}, where)
    if keys.DT in arrays and arrays[keys.DT].ndim and tuple(arrays[keys.DT].shape) != (n,):
        raise ValueError(f"{where}: array 'dt' has shape {tuple(arrays[keys.DT].shape)}, expected a scalar or ({n},)")
    for key, a in arrays.items():
        if key == keys.MEASUREMENTS:
            continue
        if key == keys.DT or a.ndim == 1:
            check_values(key, np.asarray(a), where)
            continue
        for start in range(0, n, ROWS):
            check_values(key, np.asarray(a[start : start + ROWS]), where, row0=start)
    return n, T


def _unlabelled(mode) -> bool:
    """Whether no scan of ``mode`` has a label (read in chunks: a memmap stays on disk)."""
    return all(bool((np.asarray(mode[i : i + ROWS]) == NO_LABEL).all()) for i in range(0, mode.shape[0], ROWS))


def check_complete(arrays: dict, where: str) -> None:
    """A ValueError if a scan has no truth (a NaN row of ``states``) or no label (``mode`` -1): training
    needs truth at every scan (padded tracks are for evaluation), and a label at every scan or at none (real
    flights have no mode labels and train on the state loss alone). Assumes :func:`check_arrays` passed, so
    that a row's first component tells whether it is NaN."""
    for key, a in arrays.items():
        if key not in (keys.STATES, keys.MODE) or (key == keys.MODE and _unlabelled(a)):
            continue
        for start in range(0, a.shape[0], ROWS):
            chunk = np.asarray(a[start : start + ROWS])
            bad = np.isnan(chunk[..., 0]) if key == keys.STATES else chunk == NO_LABEL
            if bad.any():
                what = "no truth (a NaN row of 'states')" if key == keys.STATES else f"no label (mode {NO_LABEL})"
                raise ValueError(f"{where}: the scan at {_first(bad, start)} has {what}; training needs truth "
                                 f"at every scan and a label at every scan or at none (padded tracks are for "
                                 f"evaluation, docs/data.md)")
