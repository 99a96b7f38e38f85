"""Issue 21, item 3: IMMNet itself is a TensorDict module that ``LASTEnv.rollout`` runs as a policy
(TorchRL's recurrent-module conventions: a primer for the carry, ``is_init`` for track starts)."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import Compose, InitTracker, TransformedEnv

from immnet import keys
from immnet.data.env import LASTEnv
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.tracking.tracker import PRETRAINED, Tracker, load_network


@pytest.fixture(scope="module")
def data():
    td = generate(12, seed=5, spec=DataSpec(T=40, min_segment=10))
    z = td[keys.MEASUREMENTS]
    z[:, 15:17] = math.nan  # missed detections
    z[0, :3] = math.nan  # a track whose first detection comes at scan 3
    z[1, 1] = math.nan  # and one that misses its second
    return td


@pytest.fixture(scope="module")
def net():
    return load_network(PRETRAINED)


def test_env_rollout_with_immnet_as_policy_gives_immnet_rollouts_states(data, net):
    """The shipped weights through ``env.rollout``: every action is ``IMMNet.rollout``'s state, bitwise."""
    env = TransformedEnv(LASTEnv(data), Compose(InitTracker(), net.make_tensordict_primer()))
    with torch.no_grad():
        ro = env.rollout(env.base_env.T, net)
        out, _ = net.rollout(data[keys.MEASUREMENTS].float())
    assert ro[keys.ACTION].shape == out[keys.STATE].shape
    assert torch.equal(torch.nan_to_num(ro[keys.ACTION], nan=1e30), torch.nan_to_num(out[keys.STATE], nan=1e30))
    # the carry went through the environment's specs: the mode probabilities of the last scan are the rollout's
    probs = ro["next", *keys.EXPERT_PROBS][:, -1]
    assert torch.equal(probs, out[keys.ROLLOUT_EXPERT_PROBS][:, -1])


def test_is_init_restarts_a_track_as_the_trackers_reset(data, net):
    """``is_init`` True for some tracks mid-sequence restarts them from the initial carry, as
    ``Tracker.step(z, reset=mask)`` does; the other tracks run on."""
    z = data[keys.MEASUREMENTS].float()
    B = z.shape[0]
    tracker = Tracker(load_network(PRETRAINED))
    tracker.reset(B)
    td = TensorDict({}, batch_size=[B])
    for t in range(z.shape[1]):
        init = torch.full((B, 1), t == 0)
        if t == 20:
            init[::3] = True
        td.set(keys.MEASUREMENT, z[:, t])
        td.set(keys.IS_INIT, init)
        with torch.no_grad():
            td = net(td)
        expected = tracker.step(z[:, t], reset=init[:, 0] if t == 20 else None)[keys.FUSED]
        started = ~torch.isnan(expected).any(-1)
        assert torch.equal(td[keys.ACTION][started], expected[started]), t
        td = TensorDict({k: td.get(("next", *k)) for k in net.carry_keys}, batch_size=[B])  # the next scan's carry


def test_the_policys_keys_are_the_carry_and_the_measurement(net):
    carry = set(net.initial_carry(2).keys(True, True))
    assert set(net.in_keys) == {keys.MEASUREMENT, keys.IS_INIT} | carry
    assert set(net.out_keys) == {keys.ACTION} | {("next", *k) for k in carry}


def test_a_policy_without_its_carry_is_refused_by_name(data, net):
    """Without the primer the carry does not come back from the environment: a clear error, not a restart."""
    z = data[keys.MEASUREMENTS].float()
    td = TensorDict({keys.MEASUREMENT: z[:, 0], keys.IS_INIT: torch.zeros(z.shape[0], 1, dtype=torch.bool)},
                    batch_size=[z.shape[0]])
    with pytest.raises(ValueError, match="make_tensordict_primer"):
        net(td)
    env = TransformedEnv(LASTEnv(data), InitTracker())
    with pytest.raises(ValueError, match="make_tensordict_primer"):
        env.rollout(3, net)
