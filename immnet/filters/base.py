"""What a method is: ``name``, ``needs`` (data keys beyond measurements) and ``track(batch)``.

``track`` maps a 3D-LAST batch (``TensorDict [B]``, ``measurements [B, T, 3]``) to a
``TensorDict [B]`` with ``state [B, T, 9]`` and, where the method has them, ``mode_probs [B, T, 4]``
over the data modes (0 CV, 1 CA, 2 CT+, 3 CT-).

No made-up output: a track has no estimate before its first detection (its first measurement
row without NaN), so every output ``[B, T, ...]`` is NaN there, and all NaN for a track with no
detection at all (:func:`output` does it for every method; the filters' own state stays finite).
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

from immnet import keys
from immnet.data.times import regular, scan_intervals
from immnet.motion import N_MODES

_DTYPES = {"float64": torch.float64, "float32": torch.float32, "double": torch.float64, "float": torch.float32}


class Method:
    """The protocol every tracker, baseline and bound follows."""

    name: str = "method"
    needs: tuple[str, ...] = ()
    ground_truth: bool = False
    """True where ``needs`` are ground truth (a bound, not a tracker): said in the error message."""
    any_interval: bool = False
    """True where ``track`` takes any interval before each scan (``immnet.data.times.scan_intervals``):
    the model-based filters, which build ``F`` and ``Q`` per track and scan (docs/baselines.md)."""
    build_options: dict = {}
    """The options ``immnet.filters.methods.build_method`` may set on this method's constructor, each with the
    constructor's default: ``checkpoint`` (a file), ``return_cov`` (give ``state_cov``), ``guard`` (a range guard,
    replaced where the configured one is not off), ``r`` (told each track's measurement std, with a checkpoint)."""

    def track(self, batch: TensorDict) -> TensorDict:  # pragma: no cover - interface
        raise NotImplementedError

    def check(self, batch: TensorDict) -> None:
        """Raise a ValueError naming the first array this method needs and ``batch`` lacks."""
        for key in (keys.MEASUREMENTS, *self.needs):
            if key not in batch.keys():
                kind = " (ground truth)" if self.ground_truth and key != keys.MEASUREMENTS else ""
                raise ValueError(f"{self.name} needs {key!r}{kind}, which this data lacks")

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"


def as_dtype(dtype) -> torch.dtype:
    if isinstance(dtype, torch.dtype):
        return dtype
    if dtype not in _DTYPES:
        raise ValueError(f"dtype must be one of {sorted(_DTYPES)}, got {dtype!r}")
    return _DTYPES[dtype]


def interval_or_intervals(batch: TensorDict, dtype, device) -> float | torch.Tensor:
    """The one interval of every scan after scan 0 of ``batch`` as a float, from which the fixed-interval fast paths
    build ``F`` and ``Q`` once (with one scan, scan 0's interval where all tracks share it: no step uses it); else,
    where they differ (per track or per scan), the intervals before each scan ``[B, T]`` (``scan_intervals``)."""
    intervals = scan_intervals(batch, dtype, device)
    if intervals.numel() == 0:
        return intervals
    if intervals.shape[1] == 1:
        first = intervals[:, 0]
        return float(first[0]) if bool((first == first[0]).all()) else intervals
    return float(intervals[0, 1]) if regular(intervals) else intervals


def data_mode_probs(probs: torch.Tensor, modes: torch.Tensor) -> torch.Tensor:
    """Expert probabilities ``[..., M]`` summed per data mode -> ``[..., 4]`` (absent modes get 0)."""
    onehot = torch.nn.functional.one_hot(modes.to(probs.device), N_MODES).to(probs.dtype)
    return probs @ onehot


def before_first_detection(z: torch.Tensor) -> torch.Tensor:
    """``[B, T]`` mask of the scans of ``z [B, T, 3]`` before each track's first detection (a row with
    no NaN component); every scan of a track without any detection."""
    detected = ~torch.isnan(z).any(-1)
    return torch.cumsum(detected.to(torch.int32), -1) == 0


def blank_before_first_detection(value: torch.Tensor, waiting: torch.Tensor) -> torch.Tensor:
    """``value [B, T, ...]`` with NaN wherever ``waiting [B, T]`` (a copy; integer tensors as they are)."""
    if not value.is_floating_point() or not waiting.any():
        return value
    mask = waiting.to(value.device).view(*waiting.shape, *([1] * (value.dim() - waiting.dim())))
    return value.masked_fill(mask, float("nan"))


def output(state: torch.Tensor, extra: dict | None = None, *, measurements: torch.Tensor) -> TensorDict:
    """A method's output ``TensorDict [B]``: ``state`` plus any non-None ``extra`` entries, each NaN
    before its track's first detection in ``measurements [B, T, 3]`` (no estimate yet)."""
    waiting = before_first_detection(measurements)
    entries = {keys.STATE: state, **(extra or {})}
    return TensorDict({key: blank_before_first_detection(value, waiting) for key, value in entries.items()
                       if value is not None}, batch_size=[state.shape[0]])
