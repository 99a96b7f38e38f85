"""A setting that is one of a few named kinds, read from configuration as a type.

Such a setting is a ``str``-valued ``enum.Enum`` (a subclass of ``Choice``) whose members' values are the
configuration's spellings: a YAML file, a checkpoint's hyper-parameters and weights.json keep their strings, and a
member is itself that string (equal to it, hashed as it, written as it by ``str``, ``format`` and ``json``), so a
constructor takes either. Each type's ``parse`` reads a spelling or a member as the member and refuses anything
else in one line; code branches on the member (``is``), never on the spelling. Configuration data that records a
member (a network's ``config``, a checkpoint's hyper-parameters) records its spelling (``spelled``).

The choices, each beside its role: ``immnet.motion.Modes`` (``modes``: one set of mode probabilities, or one per
axis or per channel), ``immnet.stages.filtering.Interaction`` (``interaction``: where a filter expert's prediction
starts) and ``immnet.stages.network.Likelihood`` (a bank's ``likelihood``: of the filter's prediction or of the
track as reported). A kind that carries data is a frozen dataclass instead (``immnet.imm.measurement``'s models;
``immnet.imm.option.Option`` for an optional component).
"""

from __future__ import annotations

from enum import Enum


class Choice(str, Enum):
    """Base of a setting's kinds (module doc). A subclass's refusal names the setting by the class's name in lower
    case (``refusal``, which a subclass may word as its own)."""

    __str__ = str.__str__
    __format__ = str.__format__

    @classmethod
    def lookup(cls, value) -> Choice | None:
        """The member ``value`` is or spells; None for anything else (another choice's member included)."""
        if isinstance(value, cls):
            return value
        if isinstance(value, Choice) or not isinstance(value, str):
            return None
        return cls._value2member_map_.get(value)

    @classmethod
    def spellings(cls) -> tuple[str, ...]:
        return tuple(kind.value for kind in cls)

    @classmethod
    def refusal(cls, value) -> str:
        """The line that refuses ``value``: the setting, the value and the spellings."""
        return f"{cls.__name__.lower()} must be one of {cls.spellings()}, got {value!r}"

    @classmethod
    def parse(cls, value) -> Choice:
        """``value`` (a spelling or a member) as the member; anything else a ValueError (``refusal``)."""
        kind = cls.lookup(value)
        if kind is None:
            raise ValueError(cls.refusal(value))
        return kind


def spelled(config):
    """Configuration data (dicts, lists, tuples) with every ``Choice`` member replaced by its spelling, a plain
    ``str``: what a checkpoint's hyper-parameters and a YAML file hold."""
    if isinstance(config, Choice):
        return config.value
    if isinstance(config, dict):
        return {k: spelled(v) for k, v in config.items()}
    if type(config) in (list, tuple):
        return type(config)(spelled(v) for v in config)
    return config
