"""LASTEnv: a TorchRL rollout of a trivial tracker, rewards against a direct numpy computation."""

import numpy as np
import torch
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import check_env_specs

from immnet.data import generate
from immnet.data.env import LASTEnv
from immnet.data.spec import DataSpec


class MeasurementAsState(torch.nn.Module):
    def forward(self, z):
        x = z.new_zeros(*z.shape[:-1], 9)
        x[..., [0, 3, 6]] = z
        return x


def test_rollout_rewards_are_minus_squared_position_error():
    d = generate(6, 0, DataSpec(T=30, min_segment=10))
    env = LASTEnv(d, dtype=torch.float64)
    check_env_specs(env)
    policy = TensorDictModule(MeasurementAsState(), in_keys=["measurement"], out_keys=["action"])
    ro = env.rollout(30, policy)
    assert ro.batch_size == torch.Size([6, 30])
    z, x = d["measurements"].numpy(), d["states"].numpy()[..., [0, 3, 6]]
    np.testing.assert_allclose(ro["next", "reward"][..., 0].numpy(), -((z - x) ** 2).sum(-1), rtol=1e-12)
    np.testing.assert_array_equal(ro["measurement"].numpy(), z)
    assert ro["next", "done"][:, -1].all() and not ro["next", "done"][:, :-1].any()
    assert (ro["t"][..., 0] == torch.arange(30)).all()
