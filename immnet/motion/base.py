"""What a motion model is: a named transition ``F(dt)`` and process noise ``Q(sigma_q, dt)``.

A model is data. It names the 3D-LAST mode it stands for (``0 CV, 1 CA, 2 CT+, 3 CT-``) so that
several experts may share a mode (CT at +3 and +8 deg/s, say). A model set is a list of models,
written in YAML with ``class_path`` / ``init_args``::

    models:
      - class_path: immnet.motion.ConstantVelocity
      - class_path: immnet.motion.CoordinatedTurn
        init_args: {turn_rate_deg: 5.0}
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import torch

from immnet.config import instantiate, load_yaml
from immnet.motion import models as m


class MotionModel:
    """One motion hypothesis. Subclasses give ``F``; ``Q`` uses the noise form ``noise`` (white / wiener /
    continuous, ``immnet.motion.models``) on the model's highest derivative (``order``: 1 acceleration, 2 jerk),
    with the z axis's ``sigma_q`` scaled by ``vertical``."""

    noise: str = "white"
    order: int = 1
    vertical: float = 1.0
    mode: int = 0
    state_dependent: bool = False
    """True where the transition depends on the state (``adaptive_ct_propagate``), not ``F`` alone."""

    @property
    def name(self) -> str:  # pragma: no cover - overridden
        raise NotImplementedError

    def F(self, dt: float = 1.0, dtype=torch.float64, device=None) -> torch.Tensor:  # pragma: no cover
        raise NotImplementedError

    def Q(self, sigma_q: float, dt: float = 1.0, dtype=torch.float64, device=None) -> torch.Tensor:
        """``Q = sigma_q^2 G G^T`` with this model's ``G`` (docs/spec.md section 3), or ``sigma_q^2 Q_c(dt)`` of
        continuous white noise (docs/baselines.md)."""
        return m.process_noise(sigma_q, dt, self.noise, dtype=dtype, device=device, order=self.order,
                               vertical=self.vertical)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name})"

    def __eq__(self, other) -> bool:
        return type(self) is type(other) and self.__dict__ == other.__dict__

    def __hash__(self) -> int:
        return hash((type(self).__name__, tuple(sorted(self.__dict__.items()))))


class ModelSet:
    """An ordered list of motion models, stacked on a leading expert dimension ``M``."""

    def __init__(self, models: Sequence[MotionModel]):
        models = list(models)
        if not models:
            raise ValueError("a model set needs at least one motion model")
        for i, model in enumerate(models):
            if not isinstance(model, MotionModel):
                raise TypeError(f"model set entry {i} is {type(model).__name__}, not a MotionModel")
        names = [model.name for model in models]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:  # names key the logs, the per-expert outputs and `kalmannet --expert`
            raise ValueError(f"a model set needs distinct experts; {', '.join(twice)} appears more than once")
        self.models = models

    def __len__(self) -> int:
        return len(self.models)

    def __iter__(self):
        return iter(self.models)

    def __getitem__(self, i):
        return self.models[i]

    def __repr__(self) -> str:
        return f"ModelSet({', '.join(self.names)})"

    @property
    def names(self) -> list[str]:
        return [model.name for model in self.models]

    @property
    def modes(self) -> torch.Tensor:
        """Data mode each expert stands for, ``[M]`` int64."""
        return torch.tensor([model.mode for model in self.models], dtype=torch.long)

    def F(self, dt=1.0, dtype=torch.float64, device=None) -> torch.Tensor:
        """Stacked transitions ``[M, 9, 9]`` (``[..., M, 9, 9]`` for a tensor ``dt [...]``, one interval per track)."""
        return torch.stack([model.F(dt, dtype=dtype, device=device) for model in self.models], -3)

    def Q(self, sigma_q, dt=1.0, dtype=torch.float64, device=None) -> torch.Tensor:
        """Stacked process noise ``[M, 9, 9]`` (``[..., M, 9, 9]`` for a tensor ``dt [...]``); ``sigma_q`` a
        scalar or one per model."""
        if isinstance(sigma_q, (int, float)):  # python numbers as they are: no tensor to read back (torch.compile)
            sq = [float(sigma_q)] * len(self)
        elif isinstance(sigma_q, (list, tuple)) and len(sigma_q) == len(self):
            sq = [float(v) for v in sigma_q]
        else:
            sq = torch.as_tensor(sigma_q, dtype=dtype).expand(len(self)).tolist()
        return torch.stack(
            [model.Q(s, dt, dtype=dtype, device=device) for model, s in zip(self.models, sq)], -3
        )

    # --- YAML -----------------------------------------------------------------------------
    @classmethod
    def from_config(cls, spec) -> "ModelSet":
        """From a YAML path, a ``{"models": [...]}`` mapping or a list of ``class_path`` entries."""
        if isinstance(spec, ModelSet):
            return spec
        if isinstance(spec, (str, Path)):
            spec = load_yaml(spec)
        if isinstance(spec, dict):
            if "models" not in spec:
                raise ValueError("a model set mapping needs a 'models' list")
            spec = spec["models"]
        if not isinstance(spec, (list, tuple)):
            raise TypeError(f"a model set is a list of models, got {type(spec).__name__}")
        return cls([m_ if isinstance(m_, MotionModel) else instantiate(m_, MotionModel) for m_ in spec])

    def to_config(self) -> dict:
        return {
            "models": [
                {"class_path": f"{type(x).__module__}.{type(x).__name__}", "init_args": x.init_args()}
                for x in self.models
            ]
        }
