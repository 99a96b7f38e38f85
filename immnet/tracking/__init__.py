"""Trained trackers in use: the streaming ``Tracker``, the bank of networks (the default), evaluation methods,
``immnet track``."""

from immnet.tracking.bank import BankMethod, NetworkBank
from immnet.tracking.methods import IMMNetMethod, KalmanNetMethod
from immnet.tracking.tracker import Tracker, load_network

__all__ = ["BankMethod", "IMMNetMethod", "KalmanNetMethod", "NetworkBank", "Tracker", "load_network"]
