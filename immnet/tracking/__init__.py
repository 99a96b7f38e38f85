"""Trained trackers in use: the streaming ``Tracker``, the bank of networks (the default), evaluation methods,
``immnet track``.

The names below load their modules (torch) when first asked for, so that ``immnet.tracking.cli`` builds
``immnet track --help`` without them."""

from immnet.lazy import lazy_names

__getattr__, __dir__, __all__ = lazy_names(__name__, {
    "BankMethod": "immnet.tracking.bank", "NetworkBank": "immnet.tracking.bank",
    "IMMNetMethod": "immnet.tracking.methods", "KalmanNetMethod": "immnet.tracking.methods",
    "Tracker": "immnet.tracking.tracker", "load_network": "immnet.tracking.tracker",
    "NetworkFilter": "immnet.tracking.network_filter",
    **dict.fromkeys(("IMMFilter", "MultiTargetTracker", "TrackFilter", "TrackReport", "TwoPointStart"),
                    "immnet.filters.multi"),
})

