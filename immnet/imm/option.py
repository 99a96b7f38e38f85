"""An optional filter component set from configuration: off, its defaults, or some of its fields."""

from __future__ import annotations

import math
from dataclasses import asdict, fields


def is_number(value) -> bool:
    """Whether ``value`` is a finite ``int`` or ``float`` (a bool is not): what a configured number must be."""
    return not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)


def positive(value, refusal: str) -> float:
    """``value`` as a float where it is a positive number (``is_number``), else a ValueError: ``refusal`` and the
    value given."""
    if not (is_number(value) and value > 0):
        raise ValueError(f"{refusal}, got {value!r}")
    return float(value)


def flag(value, name: str) -> bool:
    """``value`` where it is a bool, else a ValueError naming ``name``: a configured switch (``"false"`` would read as
    true through ``bool``)."""
    if not isinstance(value, bool):
        raise ValueError(f"{name} must be true or false, got {value!r}")
    return value


class Option:
    """Mixin of a frozen dataclass that a tracker takes as an optional setting (``RangeGuard``,
    ``AdaptiveNoise``); ``ARG`` names the constructor argument in error messages."""

    ARG = "option"

    @classmethod
    def from_config(cls, config):
        """``None``/``False`` (off: ``None``), ``True`` (the defaults), a dict of fields, or an instance."""
        if config is None or config is False:
            return None
        if config is True:
            return cls()
        if isinstance(config, cls):
            return config
        if isinstance(config, dict):
            known = sorted(f.name for f in fields(cls))
            unknown = set(config) - set(known)
            if unknown:
                raise ValueError(f"unknown {cls.__name__} field(s) {sorted(unknown)}; known: {known}")
            return cls(**config)
        raise ValueError(f"{cls.ARG} must be None, a bool, a dict of {cls.__name__} fields or an instance of {cls.__name__}, "
                         f"got {config!r}")

    def to_config(self) -> dict:
        return asdict(self)
