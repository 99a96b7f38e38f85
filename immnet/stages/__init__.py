"""The IMMNet stages as TensorDict modules, and the tracker that chains them."""

from immnet.stages.classify import (
    BayesianModeUpdate, BayesTransformerClassifier, ModeUpdate, TransformerClassifier, TrueModeUpdate, UniformMix,
)
from immnet.stages.fuse import Fuse
from immnet.stages.gain import AnalyticGain, Gain, KalmanNetGain, steady_state
from immnet.stages.network import IMMNet
from immnet.stages.predict import Predict
from immnet.stages.update import Update

__all__ = [
    "AnalyticGain", "BayesTransformerClassifier", "BayesianModeUpdate", "Fuse", "Gain", "IMMNet", "KalmanNetGain",
    "ModeUpdate", "Predict", "TransformerClassifier", "TrueModeUpdate", "UniformMix", "Update", "steady_state",
]
