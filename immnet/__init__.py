"""IMMNet: interacting multiple models with learned KalmanNet experts and a Transformer mode classifier."""

__version__ = "0.1.0"
