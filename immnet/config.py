"""Finding and building configured components (``class_path`` / ``init_args`` YAML)."""

from __future__ import annotations

from pathlib import Path

import yaml

from immnet.motion.base import instantiate

REPO_ROOT = Path(__file__).resolve().parents[1]
"""The checkout holding ``configs/`` and ``recipes/`` (an editable install or a clone)."""


def resolve_path(path: str | Path) -> Path:
    """A config path as given, else relative to the repository root; a clear error if neither exists."""
    p = Path(path)
    if p.exists():
        return p
    q = REPO_ROOT / p
    if q.exists():
        return q
    raise FileNotFoundError(f"config file not found: {path} (looked in . and {REPO_ROOT})")


def load_yaml(path: str | Path) -> dict:
    return yaml.safe_load(resolve_path(path).read_text())


def build(spec):
    """Instantiate a component from a ``class_path`` mapping or from a YAML file holding one."""
    if isinstance(spec, (str, Path)):
        spec = load_yaml(spec)
    return instantiate(spec)
