"""A Rauch-Tung-Striebel smoother of the white-jerk constant-acceleration model, at irregular times.

Per axis the state is ``x = [p, v, a]`` and the jerk is continuous white noise of spectral density
``q`` (m^2/s^5). Over an interval ``dt``::

    F = [[1, dt, dt^2/2], [0, 1, dt], [0, 0, 1]]
    Q = q [[dt^5/20, dt^4/8, dt^3/6], [dt^4/8, dt^3/3, dt^2/2], [dt^3/6, dt^2/2, dt]]

A measurement is the position, ``z = p + n``, ``n ~ N(0, s^2)`` (``s^2`` may differ per point). The
Kalman filter runs forward over the steps, then the RTS pass backward::

    C_k = P_k|k F_k+1^T P_k+1|k^-1,   x_k|K = x_k|k + C_k (x_k+1|K - F_k+1 x_k|k)

The smoothed ``[p, v, a]`` are one trajectory of the model (each the derivative of the one before, up to
the jerk noise): consistent truth states. A step without a measurement (NaN) is a point where the
smoother is evaluated only. Many tracks (flights x axes) run at once, ``[K, B]``: a track shorter than
``K`` is padded by repeating its last time (``dt = 0``: ``F = I``, ``Q = 0``, nothing changes).

The prior of the first step is diffuse (position and velocity standard deviations of 1e4 m and
1e3 m/s, acceleration 10 m/s^2, mean 0 except the position at the first measurement).
"""

from __future__ import annotations

import numpy as np

PRIOR_STD = np.array([1e4, 1e3, 10.0])


def transition(dt: np.ndarray) -> np.ndarray:
    """``F(dt) [..., 3, 3]`` of the constant-acceleration model."""
    dt = np.asarray(dt, np.float64)
    F = np.zeros((*dt.shape, 3, 3))
    F[..., 0, 0] = F[..., 1, 1] = F[..., 2, 2] = 1.0
    F[..., 0, 1] = F[..., 1, 2] = dt
    F[..., 0, 2] = dt * dt / 2.0
    return F


def jerk_noise(dt: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``Q(dt) [..., 3, 3]`` of continuous white jerk of spectral density ``q`` (broadcast with ``dt``)."""
    dt = np.asarray(dt, np.float64)
    q = np.asarray(q, np.float64)
    d2, d3 = dt * dt, dt * dt * dt
    Q = np.empty((*np.broadcast_shapes(dt.shape, q.shape), 3, 3))
    Q[..., 0, 0] = d3 * d2 / 20.0
    Q[..., 0, 1] = Q[..., 1, 0] = d2 * d2 / 8.0
    Q[..., 0, 2] = Q[..., 2, 0] = d3 / 6.0
    Q[..., 1, 1] = d3 / 3.0
    Q[..., 1, 2] = Q[..., 2, 1] = d2 / 2.0
    Q[..., 2, 2] = dt
    return Q * q[..., None, None]


def rts_smooth(t: np.ndarray, z: np.ndarray, var: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Smoothed states ``[K, B, 3]`` (position, velocity, acceleration) of ``B`` tracks.

    ``t [K, B]``: non-decreasing times (s) per track; ``z [K, B]``: the measured position (NaN: none);
    ``var [K, B]``: its variance (m^2); ``q [B]``: the jerk spectral density per track (m^2/s^5).
    """
    t, z, var = (np.asarray(a, np.float64) for a in (t, z, var))
    q = np.broadcast_to(np.asarray(q, np.float64), t.shape[1:])
    K, B = t.shape
    has = np.isfinite(z)
    x = np.zeros((B, 3))
    first = np.where(has.any(0), has.argmax(0), 0)
    x[:, 0] = np.nan_to_num(z[first, np.arange(B)])
    P = np.broadcast_to(np.diag(PRIOR_STD ** 2), (B, 3, 3)).copy()
    xf = np.empty((K, B, 3))
    Pf = np.empty((K, B, 3, 3))
    for k in range(K):
        if k:
            F = transition(t[k] - t[k - 1])
            x = np.einsum("bij,bj->bi", F, x)
            P = F @ P @ F.transpose(0, 2, 1) + jerk_noise(t[k] - t[k - 1], q)
        m = has[k]
        if m.any():
            S = P[m, 0, 0] + var[k, m]
            gain = P[m, :, 0] / S[:, None]
            x[m] += gain * (z[k, m] - x[m, 0])[:, None]
            P[m] -= gain[:, :, None] * gain[:, None, :] * S[:, None, None]
            P[m] = 0.5 * (P[m] + P[m].transpose(0, 2, 1))
        xf[k], Pf[k] = x, P
    xs = np.empty_like(xf)
    xs[-1] = xf[-1]
    for k in range(K - 2, -1, -1):
        F = transition(t[k + 1] - t[k])
        Pp = F @ Pf[k] @ F.transpose(0, 2, 1) + jerk_noise(t[k + 1] - t[k], q)
        # C = Pf F^T Pp^-1, so C^T = Pp^-1 (F Pf) (Pp and Pf symmetric)
        C = np.linalg.solve(Pp, F @ Pf[k]).transpose(0, 2, 1)
        xs[k] = xf[k] + np.einsum("bij,bj->bi", C, xs[k + 1] - np.einsum("bij,bj->bi", F, xf[k]))
    return xs
