"""Finding and building configured components (``class_path`` / ``init_args`` YAML).

The configs the package reads at run time (method registry, model sets, data sizes, ablations) and the
recipes ship inside it: a checkout's top-level ``configs/`` and ``recipes/`` are installed as
``immnet/configs`` and ``immnet/recipes`` (docs/configs.md).
A config path is looked for, in this order:

1. as given: absolute, or relative to the working directory (a user's own file wins);
2. among the packaged configs, a leading ``configs/`` dropped (``configs/model_sets/imm4.yaml`` and
   ``model_sets/imm4.yaml`` name the same file);
   ``recipes/X`` among the packaged recipes (``immnet/recipes``), which the ablations start from;
3. when the package runs from a checkout, relative to the checkout.
"""

from __future__ import annotations

import importlib
import inspect
from importlib import resources
from pathlib import Path

import yaml


REPO_ROOT = Path(__file__).resolve().parents[1]
"""The directory above the package: the checkout holding ``configs/`` and ``recipes/`` when the package
runs from one (a clone, an editable install); ``site-packages`` in an installed wheel."""


def checkout() -> Path | None:
    """The checkout the package runs from, or ``None`` for an installed wheel."""
    is_checkout = (REPO_ROOT / "pyproject.toml").is_file() and (REPO_ROOT / "configs").is_dir()
    return REPO_ROOT if is_checkout else None


def _packaged_dir(name: str) -> Path:
    """``immnet/<name>`` of an installed wheel, or its source, the checkout's ``<name>/``, in a checkout."""
    installed = resources.files("immnet") / name
    return Path(str(installed)) if installed.is_dir() else REPO_ROOT / name


def packaged_configs() -> Path:
    """The configs that ship with the package: ``immnet/configs`` of an installed wheel, or their source,
    the checkout's ``configs/``, when the package runs from a checkout."""
    return _packaged_dir("configs")


def _packaged(path: Path) -> Path:
    """Where ``path`` lies among the packaged files: ``recipes/X`` among the recipes (``immnet/recipes``, the
    checkout's ``recipes/`` in a checkout: the ablations of ``configs/ablations`` start from them), the rest among the
    configs with a leading ``configs/`` dropped."""
    if path.parts[:1] == ("recipes",):
        return _packaged_dir("recipes") / Path(*path.parts[1:])
    return packaged_configs() / (Path(*path.parts[1:]) if path.parts[:1] == ("configs",) else path)


def resolve_path(path: str | Path) -> Path:
    """``path`` found as the module doc says; ``FileNotFoundError`` listing every place looked in."""
    p = Path(path)
    if p.exists():
        return p
    looked = [Path.cwd() / p]
    if not p.is_absolute():
        candidates = [_packaged(p)]
        if checkout() is not None:
            candidates.append(REPO_ROOT / p)
        for q in candidates:
            if q.exists():
                return q
            looked.append(q)
    raise FileNotFoundError(f"config file not found: {path} (looked for {', '.join(map(str, dict.fromkeys(looked)))})")


def load_yaml(path: str | Path) -> dict:
    return yaml.safe_load(resolve_path(path).read_text())


def build(spec):
    """Instantiate a component from a ``class_path`` mapping or from a YAML file holding one."""
    if isinstance(spec, (str, Path)):
        spec = load_yaml(spec)
    return instantiate(spec)


def import_class(class_path: str, kind: type | None = None):
    """The class named by a dotted ``class_path``; ``ValueError`` naming it if it cannot be imported, or, given
    ``kind``, if it is not a class derived from ``kind`` (a function, or a class of another role, is never called)."""
    if not isinstance(class_path, str):
        raise ValueError(f"a class_path is a dotted name, got {class_path!r}")
    module_name, _, cls_name = class_path.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module_name), cls_name)
    except (ImportError, AttributeError, ValueError) as err:
        raise ValueError(f"unknown class_path {class_path!r}: {err}") from None
    if kind is not None and not (inspect.isclass(cls) and issubclass(cls, kind)):
        raise ValueError(f"class_path {class_path!r} is not a {kind.__module__}.{kind.__qualname__}")
    return cls


def instantiate(entry: dict, kind: type | None = None, **extra):
    """Build ``class_path(**init_args, **extra)``; the YAML convention of Lightning's CLI. ``kind``: the class
    ``class_path`` must derive from (``import_class``).

    ``extra`` carries what the caller knows and the YAML should not repeat (a stage's model set).
    """
    if not isinstance(entry, dict) or "class_path" not in entry:
        raise ValueError(f"expected a mapping with 'class_path', got {entry!r}")
    return import_class(entry["class_path"], kind)(**(entry.get("init_args") or {}), **extra)
