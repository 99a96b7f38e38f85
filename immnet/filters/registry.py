"""The names of the methods ``immnet evaluate --methods`` takes, found without building any (no torch).

A method is a built-in (``BUILTIN_NAMES``) or a ``<name>.yaml`` config in the working directory's
``configs/methods/`` or among the packaged ones (``METHODS_DIR``); ``immnet.filters.methods`` builds them.
"""

from __future__ import annotations

from pathlib import Path

from immnet.config import packaged_configs

METHODS_DIR = packaged_configs() / "methods"
"""Where the packaged ``<name>.yaml`` method configs live."""
USER_METHODS_DIR = Path("configs") / "methods"
"""The working directory's own method configs, looked in before ``METHODS_DIR``."""
MULTI_TARGET_FILTER = "real-imm-by-interval"
"""The per-track filter a multi-target tracker (``immnet.filters.multi.MultiTargetTracker``) builds unless told
another: the joint IMM over CV, CA and two turns tuned on real flights at the radar's scan interval
(``MULTI_TARGET_BANDS``, ``immnet.filters.multi.ByInterval``); here, torch-free, so that ``immnet track --help`` names
it."""
MULTI_TARGET_BANDS = ((3.0, "real-imm"), (6.0, "mtt-imm-5s"), (float("inf"), "real-imm-11s"))
"""``MULTI_TARGET_FILTER``'s choice, (the longest scan interval in s, the method) in order, the first band that holds
the interval: the IMM tuned at 1 s, at 4.5-5.5 s, at 10-12 s. Each was the best of the tuned IMMs by mean GOSPA on
training scenes scanned every 1, 5, 7 and 11 s (docs/multi-target.md, "Defaults"); the edges lie between those."""
BUILTIN_NAMES = ("measurements",)
"""Methods that need no config (``immnet.filters.methods.BUILTIN``)."""

ORDER = ("measurements", "imm-accurate", "imm-min", "imm-max", "imm-tuned", "imm-ekf", "imm-ekf-guard", "imm-ekf-guard-sticky", "kalmannet", "immnet", "clairvoyant-switch", "clairvoyant")
"""Row order of the results table; other configured methods follow alphabetically."""


def sort_key(name: str):
    return (ORDER.index(name), "") if name in ORDER else (len(ORDER), name)


def method_dirs(methods_dir: Path | None = None) -> list[Path]:
    """Where method configs are looked for, first first: ``methods_dir`` alone when given."""
    return [Path(methods_dir)] if methods_dir else [USER_METHODS_DIR, Path(METHODS_DIR)]


def configured_methods(methods_dir: Path | None = None) -> list[str]:
    """Every method name with a config or a built-in, in table order (not checked for importability)."""
    names = set(BUILTIN_NAMES) | {p.stem for d in method_dirs(methods_dir) if d.is_dir() for p in d.glob("*.yaml")}
    return sorted(names, key=sort_key)
