"""``LASTEnv``: the 3D-LAST scenario as a TorchRL environment, so a tracker streams with ``env.rollout``.

Each of the ``B`` environments replays one trajectory. At step ``t`` the observation is
``measurement`` ``z_t`` [B, 3] (and ``t`` [B, 1]); the action ``action`` [B, 9] is the policy's
state estimate ``x_{t|t}`` given ``z_0..z_t``; the reward is ``-||H action - H x_t||^2`` (minus the
squared position error against the true state of that step) and the next observation is
``z_{t+1}``. The episode is done after ``T`` steps::

    env = LASTEnv.from_dataset("data/test")            # or LASTEnv.generate(B, seed)
    rollout = env.rollout(env.T, policy)               # policy: a TensorDictModule measurement -> action
    rmse = (-rollout["next", "reward"]).mean().sqrt()
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from immnet import keys
from immnet.data.spec import DataSpec

OBS = "measurement"
ACTION = "action"
TIME = "t"


class LASTEnv(EnvBase):
    """Batch ``[B]`` of 3D-LAST trajectories replayed step by step (float32 by default)."""

    def __init__(self, data: TensorDictBase, dtype=torch.float32):
        missing = [k for k in (keys.STATES, keys.MEASUREMENTS) if k not in data.keys()]
        if missing:
            raise ValueError(f"LASTEnv needs the arrays {missing} (the reward needs the true states)")
        B = data.batch_size[0]
        super().__init__(batch_size=torch.Size([B]))
        self.dtype_ = dtype
        self.states = data[keys.STATES].to(dtype).contiguous()
        self.meas = data[keys.MEASUREMENTS].to(dtype).contiguous()
        self.T = self.meas.shape[1]
        self.observation_spec = Composite(
            {OBS: Unbounded(shape=(B, 3), dtype=dtype), TIME: Unbounded(shape=(B, 1), dtype=torch.int64)},
            shape=(B,),
        )
        self.action_spec = Unbounded(shape=(B, 9), dtype=dtype)
        self.reward_spec = Unbounded(shape=(B, 1), dtype=dtype)
        self.done_spec = Composite(
            {name: Categorical(2, shape=(B, 1), dtype=torch.bool) for name in ("done", "terminated", "truncated")},
            shape=(B,),
        )
        self._t = 0

    @classmethod
    def from_dataset(cls, path, indices=None, **kw) -> "LASTEnv":
        from immnet.data.storage import as_batch, load_dataset

        td, _ = load_dataset(path)
        if indices is not None:
            td = td[torch.as_tensor(indices)]
        return cls(as_batch(td), **kw)

    @classmethod
    def generate(cls, batch: int, seed: int, spec: DataSpec = DataSpec(), **kw) -> "LASTEnv":
        from immnet.data.generate import generate

        return cls(generate(batch, seed, spec), **kw)

    def _obs(self, t: int) -> dict:
        B = self.batch_size[0]
        return {OBS: self.meas[:, min(t, self.T - 1)], TIME: torch.full((B, 1), t, dtype=torch.int64)}

    def _reset(self, tensordict=None, **kwargs) -> TensorDict:
        self._t = 0
        B = self.batch_size[0]
        done = torch.zeros(B, 1, dtype=torch.bool)
        return TensorDict({**self._obs(0), "done": done, "terminated": done.clone(), "truncated": done.clone()},
                          batch_size=self.batch_size)

    def _step(self, tensordict: TensorDictBase) -> TensorDict:
        t = self._t
        est = tensordict[ACTION].to(self.dtype_)
        err = est[:, [0, 3, 6]] - self.states[:, t, [0, 3, 6]]
        reward = -(err * err).sum(-1, keepdim=True)
        self._t = t + 1
        B = self.batch_size[0]
        done = torch.full((B, 1), self._t >= self.T, dtype=torch.bool)
        return TensorDict({**self._obs(self._t), "reward": reward, "done": done,
                           "terminated": done.clone(), "truncated": torch.zeros_like(done)},
                          batch_size=self.batch_size)

    def _set_seed(self, seed):  # the data are fixed; nothing random happens in a rollout
        return seed
