"""Package names that load their modules when first asked for (PEP 562): ``immnet --help`` builds its parser from
the packages' command modules without importing torch, Lightning or wandb."""

import importlib
import sys


def lazy_names(package: str, where: dict[str, str]):
    """``(__getattr__, __dir__, __all__)`` of ``package``, whose public names ``where`` maps to the modules that
    define them; a name's module is imported the first time the name is asked for."""

    def __getattr__(name):
        if name not in where:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(where[name]), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__():
        return sorted({*vars(sys.modules[package]), *where})

    return __getattr__, __dir__, sorted(where)
