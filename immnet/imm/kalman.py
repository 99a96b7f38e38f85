"""Batched Kalman filter steps, any leading dimensions, float32 or float64, on the inputs' device.

Predict::

    x_{t|t-1} = F x_{t-1|t-1}            P_{t|t-1} = F P_{t-1|t-1} F^T + Q

Update with ``z_t = H x_t + v``, ``v ~ N(0, R)``::

    y = z_t - H x_{t|t-1}      S = H P H^T + R      K = P H^T S^{-1}
    x_{t|t} = x_{t|t-1} + K y  P_{t|t} = (I - K H) P (I - K H)^T + K R K^T  (Joseph's form, symmetrized)
    log l = -1/2 (y^T S^{-1} y + log det S + m log 2 pi)

One update for every filter (``innovation_update``): the linear one (``update``), the extended polar one
(``immnet.imm.measurement.polar_update``) and, with a learned gain, IMMNet's (``joseph``) differ only in how they form
the innovation, ``H P`` and ``S``. A float32 input is updated in float64 and rounded back (``wide_dtype``).

A measurement with any NaN component is a missed detection: the posterior is the prior and the
log-likelihood is 0 (it leaves an IMM's mode probabilities at their predicted values).

With ``H=None`` the measurement is the position ``[lx, ly, lz]`` (``x[..., 0::3]``): then
``S = P[pos, pos] + R`` and ``H P = P[pos, :]`` are strided views (no product with ``H``) and
``S^{-1}`` is the closed-form 3x3 inverse (``inv3``: its ``L D L^T`` pivots), which is much faster than a
batched LAPACK call for millions of 3x3 matrices; the one 3x3 solve of the package. A general ``H`` uses a Cholesky
solve.

Robust update (``robust=k``, Huber's weight on the innovation's Mahalanobis distance ``d = sqrt(y^T S^-1 y)``)::

    w = 1 (d <= k),  k / d (d > k)          R' = R + (1/w - 1) S, so S' = S / w and K' = w K
    x_{t|t} = x + w K y                      P_{t|t} = P - w K H P   (Joseph's form with K', R')
    log l = -1/2 (2 rho_k(d) + log det S + m log 2 pi),  rho_k(d) = d^2/2 (d <= k),  k d - k^2/2 (d > k)

The correction's size grows with ``d`` up to ``d = k`` and stays at ``k`` standard deviations beyond it (Huber's
bounded influence), and the likelihood is Huber's least-favourable density, a Gaussian core with exponential tails
(its normalizing constant, the same for every filter of an IMM, is left out, so it cancels in the mode update): an
outlier neither drags the state nor gives every filter but the widest a likelihood of ``e^{-d^2/2}``. Where
``d <= k`` the update is the plain one, bit for bit.

An outlier is one plot; a maneuver the filters' models do not hold gives far plots scan after scan. So Huber's weight
is for an isolated far plot only: a plot that follows a far one is taken by the plain update (``spare``), where a plot
is far when it lies beyond ``k`` of every filter of the track (``far``; the filters on the last axis of ``d``). A scan
without a plot leaves the track's ``spare`` as it is. The scan loops carry it per track (``immnet.imm.runner.run``,
IMMNet's filter experts, the multi-target tracker's filters); ``spare`` None weighs every plot.
"""

from __future__ import annotations

import math

import torch

from immnet.imm.option import positive
from immnet.motion import POS_VIEW

LOG_2PI = math.log(2.0 * math.pi)


def predict(x: torch.Tensor, P: torch.Tensor, F: torch.Tensor, Q: torch.Tensor):
    """``x [..., n]``, ``P [..., n, n]``, ``F``/``Q`` broadcastable to ``[..., n, n]`` -> ``(x, P)`` prior.

    Where every track shares its filters' ``F [M, n, n]`` (``P [B, M, n, n]``), ``F P F^T`` is one product per
    filter over every track, ``vec(P) (F (x) F)^T``: a few large matrix products in place of ``2 B M`` small ones."""
    x = (F @ x.unsqueeze(-1)).squeeze(-1)
    if F.dim() == 3 and P.dim() == 4 and P.shape[1] == F.shape[0] and P.shape[0] > 1:
        B, M, n, _ = P.shape
        kron_t = torch.einsum("mli,mkj->mijlk", F, F).reshape(M, n * n, n * n)  # [(i, j), (l, k)] = F_li F_kj
        FPFt = torch.bmm(P.reshape(B, M, n * n).transpose(0, 1), kron_t).transpose(0, 1).reshape(B, M, n, n)
        return x, FPFt + Q
    P = F @ P @ F.transpose(-1, -2) + Q
    return x, P


def start_state(z: torch.Tensor, R: torch.Tensor, vel_std: float, acc_std: float,
                vz_std: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """A track started at a detection ``z [B, 3]`` with covariance ``R [B, 3, 3]``: ``x = [z, 0, 0]`` per axis and
    ``P`` with the position block ``R``, velocity and acceleration variances ``vel_std^2``, ``acc_std^2`` on every axis
    (the 9-D state ``[x, vx, ax, y, vy, ay, z, vz, az]``); ``vz_std``: fused with a prior on the vertical speed,
    ``N(0, vz_std^2)`` (``check_vz_std``; ``vertical_speed_prior``: its variance ``vel_std^2 vz_std^2 / (vel_std^2 +
    vz_std^2)``)."""
    B = z.shape[0]
    x = z.new_zeros(B, 9)
    x[:, 0::3] = z
    diag = z.new_zeros(B, 9)
    diag[:, 1::3] = vel_std**2
    diag[:, 2::3] = acc_std**2
    P = torch.diag_embed(diag)
    P[:, 0::3, 0::3] = R.to(P)
    return (x, P) if vz_std is None else vertical_speed_prior(x, P, vz_std)


def vertical_speed_prior(x: torch.Tensor, P: torch.Tensor, vz_std: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``x [..., n]``, ``P [..., n, n]`` (the 9-D state first, ``vz`` its 8th entry; ``n`` 9, or 10 for the filter
    experts' ``[x, w]``) fused with the prior ``vz ~ N(0, vz_std^2)``: ``update`` measuring the vertical speed as 0
    with variance ``vz_std^2``. Every start that takes the prior takes it here."""
    H = P.new_zeros(1, P.shape[-1])
    H[0, 7] = 1.0
    x, P, _ = update(x, P, P.new_zeros(*P.shape[:-2], 1), H, float(vz_std) ** 2)
    return x, P


def check_vz_std(vz_std) -> float | None:
    """A start's prior standard deviation of the vertical speed (m/s), finite and > 0, as a float; None: no prior."""
    return None if vz_std is None else positive(vz_std, "vz_std (the start's prior std of the vertical speed, m/s) "
                                                        "must be a number > 0 or None")


def gaussian_loglik(maha: torch.Tensor, logdet: torch.Tensor, m: int) -> torch.Tensor:
    """``log N(nu; 0, S) = -1/2 (nu^T S^-1 nu + log det S + m log 2 pi)`` of an ``m``-dimensional innovation from its
    Mahalanobis distance ``maha = nu^T S^-1 nu`` and ``log det S`` (each ``[...]``): every tracker's likelihood."""
    return -0.5 * (maha + logdet + m * LOG_2PI)


def quadratic(S_inv: torch.Tensor, nu: torch.Tensor) -> torch.Tensor:
    """The squared Mahalanobis distance ``nu^T S^-1 nu`` ``[...]`` of innovations ``nu [..., m]`` from the inverse of
    their covariance ``S_inv [..., m, m]`` (``inv3``'s)."""
    return ((S_inv @ nu.unsqueeze(-1)).squeeze(-1) * nu).sum(-1)


def inv3(S: torch.Tensor):
    """Inverse and log-determinant of symmetric positive-definite 3x3 matrices ``[..., 3, 3]`` (covariances), in
    closed form by their ``L D L^T`` factorization: ``(S^{-1}, log det S)``.

    Unlike the adjugate over the determinant, whose triple products cancel, the pivots lose only what the
    matrix's conditioning costs: a float32 innovation covariance of a turn expert after a 10 s gap (position
    variances ~6e7 m^2, eigenvalues 2e3 to 1e8) had an adjugate determinant off by 2x, in a batch of the wrong
    sign (a NaN likelihood); its pivots give the log-determinant to 1e-4 and the inverse to 3e-4 of float64's.
    ``S`` is read as symmetric (its two triangles averaged); a pivot below ``eps`` times its diagonal element (a
    matrix singular to the dtype's precision) is held there, so the result stays finite."""
    a00, a11, a22 = S[..., 0, 0], S[..., 1, 1], S[..., 2, 2]
    a01 = 0.5 * (S[..., 0, 1] + S[..., 1, 0])
    a02 = 0.5 * (S[..., 0, 2] + S[..., 2, 0])
    a12 = 0.5 * (S[..., 1, 2] + S[..., 2, 1])
    eps, tiny = torch.finfo(S.dtype).eps, torch.finfo(S.dtype).tiny

    def pivot(value, diagonal):
        return torch.maximum(value, eps * diagonal.abs()).clamp_min(tiny)

    d0 = pivot(a00, a00)
    l10, l20 = a01 / d0, a02 / d0
    d1 = pivot(a11 - l10 * a01, a11)
    l21 = (a12 - l20 * a01) / d1
    d2 = pivot(a22 - l20 * a02 - l21 * l21 * d1, a22)
    # S^-1 = M^T D^-1 M with M = L^-1 = [[1, 0, 0], [m10, 1, 0], [m20, m21, 1]]
    m10, m21 = -l10, -l21
    m20 = l10 * l21 - l20
    i0, i1, i2 = d0.reciprocal(), d1.reciprocal(), d2.reciprocal()
    s00 = i0 + m10 * m10 * i1 + m20 * m20 * i2
    s01 = m10 * i1 + m20 * m21 * i2
    s02 = m20 * i2
    s11 = i1 + m21 * m21 * i2
    s12 = m21 * i2
    inv = torch.stack([torch.stack(r, -1) for r in ((s00, s01, s02), (s01, s11, s12), (s02, s12, i2))], -2)
    return inv, torch.log(d0) + torch.log(d1) + torch.log(d2)


def group_maha(nu: torch.Tensor, S: torch.Tensor, groups: list[list[int]]) -> tuple[torch.Tensor, torch.Tensor]:
    """``(d^2, log det S_gg)`` of each group ``g`` of the innovation's coordinates (``groups``, at most two
    coordinates each: ``[[0], [1], [2]]`` per axis, ``[[0, 1], [2]]`` per channel), the marginal of those coordinates:
    innovations ``nu [..., 3]``, covariances ``S [..., 3, 3]`` -> two ``[..., G]``."""
    maha, logdet = [], []
    for g in groups:
        if len(g) == 1:
            i = g[0]
            s, n = S[..., i, i], nu[..., i]
            maha.append(n * n / s)
            logdet.append(torch.log(s))
        elif len(g) == 2:
            i, j = g
            a, b, d = S[..., i, i], 0.5 * (S[..., i, j] + S[..., j, i]), S[..., j, j]
            n, m = nu[..., i], nu[..., j]
            d1 = torch.maximum(d - b * b / a, torch.finfo(S.dtype).eps * d)  # L D L^T, as inv3's pivots
            e = m - b / a * n  # the second coordinate's innovation given the first
            maha.append(n * n / a + e * e / d1)
            logdet.append(torch.log(a) + torch.log(d1))
        else:
            raise ValueError(f"group_loglik takes groups of one or two coordinates, got {g}")
    return torch.stack(maha, -1), torch.stack(logdet, -1)


def group_loglik(nu: torch.Tensor, S: torch.Tensor, groups: list[list[int]]) -> torch.Tensor:
    """``log N(nu_g; 0, S_gg)`` of each group ``g`` of the innovation's coordinates (``group_maha``'s groups), the
    marginal of those coordinates: innovations ``nu [..., 3]``, covariances ``S [..., 3, 3]`` -> ``[..., G]``."""
    return marginal_loglik(*group_maha(nu, S, groups), groups)


def marginal_loglik(maha: torch.Tensor, logdet: torch.Tensor, groups: list[list[int]]) -> torch.Tensor:
    """Each group's Gaussian log-likelihood ``[..., G]`` from ``group_maha``'s ``(d^2, log det S_gg)`` (or Huber's
    ``2 rho_k(d)`` in place of ``d^2``: ``huber``)."""
    return torch.stack([gaussian_loglik(maha[..., k], logdet[..., k], len(g)) for k, g in enumerate(groups)], -1)


def small_matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` for a small inner dimension ``k`` (a measurement's 3), as ``sum_k a[..., :, k] b[..., k, :]``:
    on CPU a batched GEMM of millions of 10x3 matrices is several times slower than three broadcast
    products, which ``torch.compile`` fuses into one loop."""
    out = a[..., :, :1] * b[..., :1, :]
    for k in range(1, a.shape[-1]):
        out = out + a[..., :, k : k + 1] * b[..., k : k + 1, :]
    return out


def wide_dtype(dtype: torch.dtype, device) -> torch.dtype:
    """The dtype an update runs in: float64 for float32 input (a large prior's terms cancel to a small posterior:
    ``joseph``), except where float64 is unavailable (MPS)."""
    return dtype if dtype == torch.float64 or torch.device(device).type == "mps" else torch.float64


def joseph_form(P: torch.Tensor, K: torch.Tensor, HP: torch.Tensor, S: torch.Tensor) -> torch.Tensor:
    """The posterior covariance ``(I - K H) P (I - K H)^T + K R K^T`` of any gain ``K [..., n, m]``, from the prior
    ``P [..., n, n]``, its measured rows ``HP = H P [..., m, n]`` and the innovation covariance ``S = H P H^T + R``
    ``[..., m, m]``, expanded as ``P - K H P - (K H P)^T + K S K^T`` and symmetrized; in the inputs' dtype."""
    KHP = small_matmul(K, HP)
    post = P - KHP - KHP.transpose(-1, -2) + small_matmul(small_matmul(K, S), K.transpose(-1, -2))
    return 0.5 * (post + post.transpose(-1, -2))


def joseph(P: torch.Tensor, K: torch.Tensor, r2: torch.Tensor) -> torch.Tensor:
    """The posterior covariance of any gain ``K [..., n, 3]`` (Joseph's form, ``joseph_form``: positive
    semi-definite for every ``K``, the learned gains' too), ``P [..., n, n]``, ``H`` the position rows (0, 3, 6 of the
    state layout), ``R = r2 I`` (``r2`` broadcastable to ``[..., 1, 1]``), or ``R = r2`` where ``r2`` is a covariance
    ``[..., 3, 3]`` (each detection's).

    The expanded form's terms are of the prior's size while the result can be ten orders smaller: after a 10 s gap
    under a large learned process noise the prior's position variance reaches 1e10 m^2 and the posterior's is
    ``r^2``. In float32 the rounding of those terms is larger than the result, a negative variance and a NaN track a
    scan later, so a float32 covariance is updated in float64 (``wide_dtype``) and rounded back."""
    wide = wide_dtype(P.dtype, P.device)
    Pw, Kw = P.to(wide), K.to(wide)
    HP = Pw[..., POS_VIEW, :]
    S = HP[..., POS_VIEW] + as_covariance(r2.to(wide), Pw)
    return joseph_form(Pw, Kw, HP, S).to(P.dtype)


def as_covariance(r2: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """The measurement covariance ``R`` of ``r2``: ``r2 I`` for a variance broadcasting as ``[..., 1, 1]`` (or a 0-d
    one), ``r2`` itself for a covariance ``[..., 3, 3]``; in ``like``'s dtype and device where it builds ``I``."""
    if r2.dim() >= 2 and r2.shape[-1] == 3:
        return r2
    return r2 * torch.eye(3, dtype=like.dtype, device=like.device)


def check_robust(robust) -> float | None:
    """``robust`` as Huber's ``k`` of the update (``immnet.imm.kalman``'s module doc): None (off) or a positive number."""
    return None if robust is None else positive(robust, "robust must be None (off) or Huber's k, a positive number "
                                                        "of standard deviations")


def huber(maha: torch.Tensor, k: float, spare: torch.Tensor | None = None):
    """Huber's weight ``w = min(1, k / d)`` of an innovation of squared Mahalanobis distance ``maha = d^2`` and the
    ``2 rho_k(d)`` that replaces ``d^2`` in its log-likelihood (module doc), each ``[...]``: ``(w, 2 rho_k(d))``; exactly
    ``(1, maha)`` where ``d <= k`` and where ``spare`` (bool, broadcasting to ``maha``: the plot follows a far one)."""
    out = torch.sqrt(maha.detach()) > k
    if spare is not None:
        out = out & ~spare
    d = torch.sqrt(torch.where(out, maha, torch.ones_like(maha)))  # no sqrt(0) in the graph: its gradient is inf
    w = torch.where(out, k / d, torch.ones_like(d))
    return w, torch.where(out, 2 * k * d - k * k, maha)


def far(maha: torch.Tensor, k: float, missed: torch.Tensor, spare: torch.Tensor) -> torch.Tensor:
    """The ``spare`` of the next scan (module doc): whether this scan's plot lies beyond ``k`` of every filter,
    ``maha [..., M]`` their squared Mahalanobis distances, ``missed [..., M]`` or ``[..., 1]`` (bool: no plot this
    scan), ``spare [..., 1]`` this scan's: ``[..., 1]`` bool, ``spare`` where the plot is missed."""
    return torch.where(missed.any(-1, keepdim=True), spare, maha.amin(-1, keepdim=True) > k * k)


def _as_cov(R: torch.Tensor | float, m: int, like: torch.Tensor) -> torch.Tensor:
    """``R`` as ``[..., m, m]``: a covariance, or a variance ``[...]`` times ``I_m``."""
    R = torch.as_tensor(R, dtype=like.dtype, device=like.device)
    if R.dim() >= 2 and R.shape[-2:] == (m, m):
        return R
    return R[..., None, None] * torch.eye(m, dtype=like.dtype, device=like.device)


def update(x, P, z, H=None, R=1.0, robust: float | None = None, spare: torch.Tensor | None = None):
    """One measurement update; returns ``(x_post, P_post, loglik)``, and ``far`` with ``spare`` (``innovation_update``).

    ``x [..., n]``, ``P [..., n, n]``, ``z [..., m]`` (NaN anywhere = missed), ``H [m, n]`` or None
    (positions of the 9-D state), ``R`` a covariance ``[..., m, m]`` or a variance ``[...]``/scalar.
    ``loglik [...]`` is the Gaussian log-density of the innovation, 0 where the measurement is missed.
    ``robust``: Huber's ``k`` (module doc), None: the plain update. The update is ``innovation_update``'s.
    """
    dtype = x.dtype
    wide = wide_dtype(dtype, x.device)
    x, P, z = x.to(wide), P.to(wide), z.to(wide)
    missed = torch.isnan(z).any(-1)
    if H is None:
        Hx = x[..., 0::3]
        HP = P[..., 0::3, :]
        S = HP[..., 0::3] + _as_cov(R, 3, x)
    else:
        H = H.to(dtype=wide, device=x.device)
        Hx = (H @ x.unsqueeze(-1)).squeeze(-1)
        HP = H @ P
        S = HP @ H.transpose(-1, -2) + _as_cov(R, H.shape[-2], x)
    nu = torch.where(missed[..., None], torch.zeros_like(z), z - Hx)
    return narrow(innovation_update(x, P, nu, HP, S, missed, robust, spare), dtype)


def narrow(out: tuple, dtype) -> tuple:
    """``innovation_update``'s ``(x, P, loglik[, far])`` with the first three in ``dtype``."""
    return (*(v.to(dtype) for v in out[:3]), *out[3:])


def innovation_update(x, P, nu, HP, S, missed, robust: float | None = None, spare: torch.Tensor | None = None):
    """The Kalman update every model-based filter runs, linear or extended: ``(x_post, P_post, loglik)`` from the
    prior ``x [..., n]``, ``P [..., n, n]``, the innovation ``nu [..., m]`` (0 where missed), the measured rows ``HP =
    H P [..., m, n]`` (``H`` the measurement's Jacobian for an extended filter), ``S = H P H^T + R [..., m, m]`` and
    ``missed [...]`` (bool)::

        K = (H P)^T S^-1     x_post = x + K nu     P_post = joseph_form(P, K, H P, S)     loglik = log N(nu; 0, S)

    ``S^-1`` is ``inv3``'s for ``m = 3``, a Cholesky solve otherwise. ``robust``: Huber's ``k`` (module doc: ``K -> w
    K``, ``S -> S / w``), with ``spare [..., 1]`` (bool: the plot follows a far one, the filters on the last batch axis)
    an isolated far plot's only, and a fourth output, the next scan's ``spare`` (``far``). Where a measurement is missed
    the prior is kept and ``loglik`` is 0. In the inputs' dtype (``update`` and the polar update give it float64 for
    float32 input, ``wide_dtype``)."""
    m = nu.shape[-1]
    if m == 3:
        Si, logdet = inv3(S)
    else:
        L = torch.linalg.cholesky(S)
        Si = torch.cholesky_inverse(L)
        logdet = 2.0 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
    K = small_matmul(HP.transpose(-1, -2), Si)
    maha = quadratic(Si, nu)
    after = None
    if robust is not None:
        if spare is not None:
            after = far(maha, robust, missed, spare)
        w, maha = huber(maha, robust, spare)
        K = K * w[..., None, None]
        S = S / w[..., None, None]
    x_post = x + (K @ nu.unsqueeze(-1)).squeeze(-1)
    P_post = joseph_form(P, K, HP, S)
    loglik = gaussian_loglik(maha, logdet, m)
    tail = () if after is None else (after,)
    if not torch.is_grad_enabled() and missed.device.type == "cpu" and not torch.compiler.is_compiling() and not bool(missed.any()):
        return x_post, P_post, loglik, *tail  # nothing missed: skip three passes over P (CPU only, no sync)
    # Broadcast ``missed`` over what F, Q or R may have added in front, then keep the prior.
    keep = missed.expand(loglik.shape)
    x_post = torch.where(keep[..., None], x.expand_as(x_post), x_post)
    P_post = torch.where(keep[..., None, None], P.expand_as(P_post), P_post)
    loglik = torch.where(keep, torch.zeros_like(loglik), loglik)
    return x_post, P_post, loglik, *tail
