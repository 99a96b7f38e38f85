"""What the default tracker (the bank, immnet.tracking.bank) does not spend time on, each held without a timed
assertion (BENCHMARKS.md "The default tracker against a filter" measures the time): work whose result is thrown away.
Each test counts the calls of the work it names."""

import numpy as np
import pytest
import torch
from scipy.linalg import solve_discrete_are

import immnet.stages.gain as gain
from immnet.motion import ModelSet
from immnet.stages.filtering import KalmanNetFilterGain
from immnet.stages.gain import KalmanNetGain


@pytest.fixture
def riccati_calls(monkeypatch):
    """The number of steady-state Riccati solves (``immnet.stages.gain.steady_state``) made while a test runs."""
    calls = []
    real = gain.steady_state

    def counted(*args, **kwargs):
        calls.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(gain, "steady_state", counted)
    return calls


def test_filter_experts_with_kalmannet_do_not_solve_for_a_gain_they_do_not_use(riccati_calls):
    """KalmanNetFilterGain adds its learned correction to each filter expert's own Kalman gain, so building one solves
    no steady-state Riccati equation (2,000 iterations per network: most of a shipped network's load) and keeps no
    K_ss; KalmanNet's own gain, whose base is that steady-state gain, still solves it: SciPy's Riccati solution's."""
    ms = ModelSet.from_config("configs/model_sets/imm4.yaml")
    stage = KalmanNetFilterGain(ms)
    assert riccati_calls == []
    assert "K_ss" not in dict(stage.named_buffers()) and not hasattr(stage, "K_ss")
    plain = KalmanNetGain(ms, init_sigma_q=1.0, init_r=4.0)
    assert len(riccati_calls) == 1
    F, Q = ms.F(1.0).numpy(), ms.Q(1.0, 1.0).numpy()
    H = np.zeros((3, 9))
    H[0, 0] = H[1, 3] = H[2, 6] = 1.0
    R = 16.0 * np.eye(3)
    for m in range(len(ms)):
        P = solve_discrete_are(F[m].T, H.T, Q[m], R)  # the prior covariance's fixed point
        K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
        np.testing.assert_allclose(plain.K_ss[m].double().numpy(), K, rtol=1e-4, atol=1e-6)


def test_the_bank_reads_each_members_file_once(monkeypatch):
    """Building the shipped bank reads (and checksums) each of its six files once, not once for its modes and again
    for its weights; the members are the networks ``load_network`` gives, to the bit."""
    import immnet.tracking.bank as bank
    import immnet.tracking.networks as networks
    from immnet.checkpoints import BANK_MEMBERS, shipped
    from immnet.tracking.networks import load_network

    read = []
    real = networks.read_checkpoint
    for module in (bank, networks):  # where the bank reads them, and where load_network does
        monkeypatch.setattr(module, "read_checkpoint", lambda path: read.append(path) or real(path))
    built = bank.NetworkBank.from_names()
    monkeypatch.undo()
    assert sorted(map(str, read)) == sorted(str(shipped(m)) for m in BANK_MEMBERS)
    for name, net in built.members.items():
        alone = load_network(shipped(name), guard=None)
        assert net.config == alone.config
        mine, theirs = net.state_dict(), alone.state_dict()
        assert mine.keys() == theirs.keys() and all(torch.equal(mine[k], theirs[k]) for k in mine)
