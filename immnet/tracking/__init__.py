"""Trained trackers in use: the streaming ``Tracker``, evaluation methods, ``immnet track``."""

from immnet.tracking.methods import IMMNetMethod, KalmanNetMethod
from immnet.tracking.tracker import Tracker, load_network

__all__ = ["IMMNetMethod", "KalmanNetMethod", "Tracker", "load_network"]
