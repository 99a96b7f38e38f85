"""Trained trackers in use: the streaming ``Tracker``, the bank of networks (the default), evaluation methods,
``immnet track``.

The names below load their modules (torch) when first asked for, so that ``immnet.tracking.cli`` builds
``immnet track --help`` without them."""

import importlib

_WHERE = {
    "BankMethod": "immnet.tracking.bank", "NetworkBank": "immnet.tracking.bank",
    "IMMNetMethod": "immnet.tracking.methods", "KalmanNetMethod": "immnet.tracking.methods",
    "Tracker": "immnet.tracking.tracker", "load_network": "immnet.tracking.tracker",
}
__all__ = sorted(_WHERE)


def __getattr__(name):
    if name not in _WHERE:
        raise AttributeError(f"module 'immnet.tracking' has no attribute {name!r}")
    value = getattr(importlib.import_module(_WHERE[name]), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted({*globals(), *__all__})
