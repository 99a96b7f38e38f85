"""Filters for real motion (docs/baselines.md, "Filters for real flights"): continuous white-noise process
noise (white acceleration, white jerk) against its closed form, a vertical share of it, filters told each
track's r, the decoupled IMM (one IMM per axis, ``immnet.filters.per_axis``) and the IMM per channel
(``IMMTracker(modes="channel")``) against FilterPy's ``IMMEstimator`` run per group at irregular intervals with
missed detections."""

import numpy as np
import pytest
import torch
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import IMMEstimator, KalmanFilter
from tensordict import TensorDict
from test_irregular_intervals import SCANS, _irregular, _waiting

from immnet import keys
from immnet.data.times import scan_intervals
from immnet.filters import KalmanFilterTracker, initial_state
from immnet.filters.per_axis import PerAxisIMMTracker, axis_blocks
from immnet.motion import ConstantAcceleration, ConstantVelocity, CoordinatedTurn, ModelSet, Singer, measurement_matrix


@pytest.mark.parametrize("order,model", [(2, ConstantVelocity), (3, ConstantAcceleration)], ids=["cv", "ca"])
@pytest.mark.parametrize("dt", [0.5, 1.0, 4.8])
def test_continuous_noise_is_filterpys_closed_form(order, model, dt):
    """White acceleration (CV) and white jerk (CA): each axis block is FilterPy's ``Q_continuous_white_noise``
    with spectral density ``sigma_q^2``; ``vertical`` scales the z axis's sigma_q."""
    sq, vertical = 0.7, 0.4
    Q = model(noise="continuous", vertical=vertical).Q(sq, dt)
    ref = Q_continuous_white_noise(dim=order, dt=dt, spectral_density=sq**2)
    blocks = axis_blocks(Q)
    for a, scale in enumerate((1.0, 1.0, vertical**2)):
        np.testing.assert_allclose(blocks[a, :order, :order].numpy(), scale * ref, rtol=1e-12, atol=0)
    off = Q.clone()
    for a in range(3):
        off[3 * a : 3 * a + 3, 3 * a : 3 * a + 3] = 0
    assert not off.any()


def test_the_vertical_share_leaves_the_default_noise_bitwise_unchanged():
    for model in (ConstantVelocity(), ConstantAcceleration(), CoordinatedTurn(5.0)):
        assert "vertical" not in model.init_args()
        assert torch.equal(model.Q(0.3, 2.5), type(model)(**model.init_args()).Q(0.3, 2.5))
    with pytest.raises(ValueError, match="vertical"):
        ConstantVelocity(vertical=-1.0)
    with pytest.raises(ValueError, match="noise kind"):
        ConstantVelocity(noise="pink").Q(1.0, 1.0)


def test_a_filter_told_r_uses_each_tracks_own_r():
    """``r: data``: the Kalman filter of each track equals the same filter built with that track's r."""
    data = _irregular(*SCANS["4.5-5.5 s"], seed=3)
    model = ConstantAcceleration(noise="continuous")
    told = KalmanFilterTracker(model, "data", 0.5).track(data)[keys.STATE]
    for b in range(data.batch_size[0]):
        own = KalmanFilterTracker(model, float(data[keys.R][b]), 0.5).track(data[b : b + 1])[keys.STATE][0]
        torch.testing.assert_close(told[b], own, rtol=1e-12, atol=1e-9, equal_nan=True)
    with pytest.raises(ValueError, match="needs 'r'"):
        KalmanFilterTracker(model, "data", 0.5).track(data.exclude(keys.R))
    with pytest.raises(ValueError, match="'data'"):
        KalmanFilterTracker(model, "told", 0.5)


PER_AXIS = [([0, 1, 2], [0]), ([3, 4, 5], [1]), ([6, 7, 8], [2])]  # (its states, its measured coordinates) per group
PER_CHANNEL = [([0, 1, 2, 3, 4, 5], [0, 1]), ([6, 7, 8], [2])]  # the horizontal plane (x, y), the vertical (z)


def _filterpy_per_group(ms: ModelSet, sigma_q, p_stay, batch: TensorDict, b: int, groups):
    """One FilterPy ``IMMEstimator`` per group of ``groups`` (its states of the 9-D state and the coordinates it
    measures) for track ``b``, each over Kalman filters fed each scan's blocks of the models' F and Q; a missed scan
    keeps the priors and the predicted mode probabilities (mu = cbar). Returns the states ``[T, 9]`` and each group's
    mode probabilities ``[T, G, M]``."""
    z, r = batch[keys.MEASUREMENTS][b].numpy(), float(batch[keys.R][b])
    dt = scan_intervals(batch)[b]
    x0, P0 = initial_state(batch[keys.MEASUREMENTS][b : b + 1], r)
    M = len(ms)
    Pi = np.full((M, M), (1 - p_stay) / (M - 1))
    np.fill_diagonal(Pi, p_stay)
    out, mu = np.zeros((len(z), 9)), np.zeros((len(z), len(groups), M))
    for c, (idx, cols) in enumerate(groups):
        n, m = len(idx), len(cols)
        kfs = []
        for _ in range(M):
            kf = KalmanFilter(n, m)
            kf.x, kf.P = x0[0, idx].numpy().copy(), P0[0][np.ix_(idx, idx)].numpy().copy()
            kf.H = np.zeros((m, n))
            for row, col in enumerate(cols):
                kf.H[row, 3 * col - 3 * cols[0]] = 1.0
            kf.R = r * r * np.eye(m)
            kfs.append(kf)
        imm = IMMEstimator(kfs, np.full(M, 1.0 / M), Pi)
        out[0, idx], mu[0, c] = x0[0, idx].numpy(), 1.0 / M
        for t in range(1, len(z)):
            d = float(dt[t])
            for j, kf in enumerate(kfs):
                kf.F = ms[j].F(d).numpy()[np.ix_(idx, idx)]
                kf.Q = ms[j].Q(sigma_q[j], d).numpy()[np.ix_(idx, idx)]
            imm.predict()
            if np.isnan(z[t]).any():
                for kf in kfs:
                    kf.x, kf.P = kf.x_prior.copy(), kf.P_prior.copy()
                imm.mu = imm.cbar.copy()
                imm._compute_mixing_probabilities()
                imm._compute_state_estimate()
            else:
                imm.update(z[t, cols])
            out[t, idx], mu[t, c] = imm.x.ravel(), imm.mu
    return out, mu


@pytest.mark.parametrize("singer", [False, True], ids=["cv-ca", "cv-ca-singer"])
@pytest.mark.parametrize("scans", list(SCANS), ids=list(SCANS))
def test_per_axis_imm_equals_filterpy_per_axis(scans, singer):
    """The decoupled IMM (CV white acceleration + CA white jerk, a vertical share, told r; and with a third,
    Singer filter, as ``real-imm-singer``) at irregular scans with missed detections and a gap equals three
    FilterPy IMMs, one per axis (1e-9)."""
    data = _irregular(*SCANS[scans], seed=4, B=2, T=120)
    models = [ConstantVelocity(noise="continuous", vertical=0.5), ConstantAcceleration(noise="continuous", vertical=0.3)]
    sigma_q, p_stay = [0.2, 1.1], 0.97
    if singer:
        models, sigma_q = models + [Singer(tau=2.0, vertical=0.7)], sigma_q + [0.6]
    ms = ModelSet(models)
    out = PerAxisIMMTracker(ms, "data", sigma_q, p_stay).track(data)
    assert out[keys.EXPERT_PROBS].shape == (2, 120, 3, len(ms))
    for b in range(2):
        ref, mu = _filterpy_per_group(ms, sigma_q, p_stay, data, b, PER_AXIS)
        keep = ~_waiting(data[keys.MEASUREMENTS][b].numpy())
        np.testing.assert_allclose(out[keys.STATE][b][keep].numpy(), ref[keep], rtol=1e-9, atol=1e-9 * np.abs(ref).max())
        np.testing.assert_allclose(out[keys.EXPERT_PROBS][b][keep].numpy(), mu[keep], rtol=0, atol=1e-7)


def test_per_axis_imm_of_one_model_is_the_kalman_filter():
    """With one model the decoupled IMM is the 9-D Kalman filter of a block-diagonal model (r isotropic)."""
    data = _irregular(*SCANS["0.5-6 s"], seed=5)
    model = ConstantAcceleration(noise="continuous", vertical=0.2)
    one = PerAxisIMMTracker(ModelSet([model]), 3.0, 0.8).track(data)[keys.STATE]
    kf = KalmanFilterTracker(model, 3.0, 0.8).track(data)[keys.STATE]
    torch.testing.assert_close(one, kf, rtol=1e-9, atol=1e-7, equal_nan=True)
    assert measurement_matrix().shape == (3, 9)



@pytest.mark.parametrize("sigma_q", [[0.2, 1.1], 0.7], ids=["per-model", "one"])
def test_scaled_is_the_imm_configured_with_that_noise(sigma_q):
    """``scaled(f)``: the same IMM built with every ``sigma_q`` times ``f``, to the bit; the original unchanged."""
    data = _irregular(*SCANS["0.5-6 s"], seed=6, B=2, T=120)
    ms = ModelSet([ConstantVelocity(noise="continuous", vertical=0.5), ConstantAcceleration(noise="continuous")])
    imm = PerAxisIMMTracker(ms, "data", sigma_q, 0.97)
    times = [v * 0.3 for v in sigma_q] if isinstance(sigma_q, list) else sigma_q * 0.3
    got = imm.scaled(0.3).track(data)[keys.STATE]
    torch.testing.assert_close(got, PerAxisIMMTracker(ms, "data", times, 0.97).track(data)[keys.STATE], rtol=0, atol=0,
                               equal_nan=True)
    plain = imm.track(data)[keys.STATE]
    assert imm.sigma_q == sigma_q and not torch.equal(torch.nan_to_num(got), torch.nan_to_num(plain))


@pytest.mark.parametrize("modes", ["joint", "channel"])
def test_a_joint_imms_scaled_is_the_imm_configured_with_that_noise(modes):
    """``IMMTracker.scaled(f)`` (the joint IMM's, and with modes per channel, whose ``track`` runs a step network it
    builds once): the same IMM built with every ``sigma_q`` times ``f``, to the bit, after the original has tracked."""
    from immnet.filters import IMMTracker

    data = _irregular(*SCANS["0.5-6 s"], seed=6, B=2, T=120)
    ms = ModelSet([ConstantVelocity(noise="continuous", vertical=0.5), ConstantAcceleration(noise="continuous")])
    imm = IMMTracker(ms, "data", [0.2, 1.1], 0.97, modes=modes)
    plain = imm.track(data)[keys.STATE]
    got = imm.scaled(0.3).track(data)[keys.STATE]
    want = IMMTracker(ms, "data", [0.2 * 0.3, 1.1 * 0.3], 0.97, modes=modes).track(data)[keys.STATE]
    torch.testing.assert_close(got, want, rtol=0, atol=0, equal_nan=True)
    assert not torch.equal(torch.nan_to_num(got), torch.nan_to_num(plain))

def test_per_axis_imm_tracks_a_batch_of_nine():
    """Nine tracks, whose starts ``[9, 9]`` are no matrix to split (they were once read as one and refused): each
    track's state is the one it has tracked alone."""
    data = _irregular(*SCANS["0.5-6 s"], seed=7, B=9, T=120)
    imm = PerAxisIMMTracker(ModelSet([ConstantVelocity(), ConstantAcceleration()]), 4.0, 0.5)
    together = imm.track(data)[keys.STATE]
    for b in (0, 8):
        torch.testing.assert_close(together[b], imm.track(data[b : b + 1])[keys.STATE][0], rtol=1e-12, atol=1e-9,
                                   equal_nan=True)


def test_axis_blocks_take_matrices_and_axis_states_take_states():
    """A batch of nine states ``[9, 9]`` is split by ``axis_states`` (each axis's position, velocity, acceleration);
    ``axis_blocks`` takes only ``[..., 9, 9]`` matrices and refuses a state in one line."""
    from immnet.motion.models import axis_states

    x = torch.arange(81.0).reshape(9, 9)
    for a in range(3):
        torch.testing.assert_close(axis_states(x)[a], x[:, 3 * a : 3 * a + 3], rtol=0, atol=0)
        torch.testing.assert_close(axis_blocks(x)[a], x[3 * a : 3 * a + 3, 3 * a : 3 * a + 3], rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"expected \[\.\.\., 9, 9\] matrices"):
        axis_blocks(torch.zeros(4, 9))


def test_per_axis_imm_refuses_a_turn():
    with pytest.raises(ValueError, match="couple the axes"):
        PerAxisIMMTracker(ModelSet([ConstantVelocity(), CoordinatedTurn(3.0)]), 4.0, 1.0)


@pytest.mark.parametrize("scans", list(SCANS), ids=list(SCANS))
def test_channel_imm_equals_two_filterpy_imms(scans):
    """Modes per channel (``IMMTracker(modes="channel")``, IMMNet's step with nothing learned): CV, CA and two
    coordinated turns (which couple x and y, not z), the horizontal plane and the vertical each with mode
    probabilities of its own, at irregular scans with missed detections and a gap, equal two FilterPy IMMs per track
    (horizontal 6-D, vertical 3-D): states to 1e-9 of their scale, each channel's mode probabilities to 1e-7."""
    from immnet.filters import IMMTracker

    data = _irregular(*SCANS[scans], seed=4, B=2, T=120)
    assert not torch.isnan(data[keys.MEASUREMENTS][:, 0]).any()  # detected at the first scan (module doc of _linear_network)
    ms = ModelSet([ConstantVelocity(noise="continuous", vertical=0.5), ConstantAcceleration(noise="continuous", vertical=0.3),
                   CoordinatedTurn(3.0, noise="continuous"), CoordinatedTurn(-3.0, noise="continuous")])
    sigma_q, p_stay = [0.2, 1.1, 0.5, 0.5], 0.95
    tracker = IMMTracker(ms, "data", sigma_q, p_stay, modes="channel", return_experts=True)
    out = tracker.track(data)
    assert out[keys.EXPERT_PROBS].shape == (2, 120, 2, 4) and out[keys.MODE_PROBS].shape == (2, 120, 4)
    assert out[keys.EXPERT_POST].shape == (2, 120, 4, 9)
    for b in range(2):
        ref, mu = _filterpy_per_group(ms, sigma_q, p_stay, data, b, PER_CHANNEL)
        np.testing.assert_allclose(out[keys.STATE][b].numpy(), ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
        np.testing.assert_allclose(out[keys.EXPERT_PROBS][b].numpy(), mu, rtol=0, atol=1e-7)
    # the joint IMM of the same models is another tracker; per axis refuses the turns, per channel takes them
    joint = IMMTracker(ms, "data", sigma_q, p_stay).track(data)[keys.STATE]
    assert (joint - out[keys.STATE]).abs().amax() > 1e-2
    with pytest.raises(ValueError, match="couple the groups"):
        IMMTracker(ms, "data", sigma_q, p_stay, modes="axis")
    with pytest.raises(ValueError, match="modes must be one of"):
        IMMTracker(ms, "data", sigma_q, p_stay, modes="plane")
