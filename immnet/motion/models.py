"""Motion models of 3D-LAST (docs/spec.md section 2) in the 9-D layout.

State ``x = [lx, vx, ax, ly, vy, ay, lz, vz, az]``; every function is batched in torch.

* CV, per axis ``[[1, dt, 0], [0, 1, 0], [0, 0, 0]]`` (acceleration is zero);
* CA, per axis ``[[1, dt, dt^2/2], [0, 1, dt], [0, 0, 1]]``;
* Singer (acceleration reverting to zero with time constant ``tau``), per axis ``exp(A dt)`` (``singer_block``);
* CT(w), coordinated turn in the horizontal plane::

      lx' = lx + sin(w dt)/w vx - (1 - cos(w dt))/w vy     vx' = cos(w dt) vx - sin(w dt) vy
      ly' = ly + (1 - cos(w dt))/w vx + sin(w dt)/w vy     vy' = sin(w dt) vx + cos(w dt) vy
      ax' = -w vy'                                         ay' = w vx'   (centripetal)

  with the z axis as CV.

Process noise ``Q = sigma_q^2 G G^T`` with ``G`` per axis ``[dt^2/2, dt, 0]`` (white-noise
acceleration) or ``[dt^2/2, dt, 1]`` (Wiener-process acceleration, the textbook CA filter); or
``continuous``: the highest derivative a continuous white noise of spectral density ``q = sigma_q^2``,
integrated exactly over the interval (Bar-Shalom, Li & Kirubarajan, sections 6.2.2 and 6.2.3)::

    CV, white acceleration   q [[dt^3/3, dt^2/2, 0], [dt^2/2, dt, 0], [0, 0, 0]]
    CA, white jerk           q [[dt^5/20, dt^4/8, dt^3/6], [dt^4/8, dt^3/3, dt^2/2], [dt^3/6, dt^2/2, dt]]

whose variance grows linearly with time, so that one ``q`` fits any scan interval (docs/baselines.md).
"""

from __future__ import annotations

import math

import torch

from immnet.choice import Choice
from immnet.labels import N_MODES

DEG = math.pi / 180.0

TURN_RATE_LIMIT_DEG = 30.0
"""The fastest turn a tracker's rate estimate may reach (deg/s): an aircraft's limit (30 deg/s is 4.9 g at
150 m/s), not a data set's range. A turn filter bounded at its prior's edge (3D-LAST's 10 deg/s) holds a
faster turn's rate below the truth and falls behind the target (docs/robustness.md)."""
CV, CA, CT_POS, CT_NEG = range(N_MODES)
"""The data modes by name (the one set of mode constants)."""
RATE = 9
"""The turn rate's slot in a filter's augmented state ``[x (9), w]``."""
N_AUG = 10

POS = (0, 3, 6)
VEL = (1, 4, 7)
ACC = (2, 5, 8)
POS_VIEW, VEL_VIEW, ACC_VIEW = slice(0, 7, 3), slice(1, 8, 3), slice(2, 9, 3)  # the same, read as views (no copy)
AXES = 3  # Cartesian axes, each a block [l, v, a] of the state
AXIS_OF = (0, 0, 0, 1, 1, 1, 2, 2, 2, 0)
"""The axis of each coordinate of ``[x, w]`` (the turn rate ``w`` with the first, horizontal, axis)."""


class Modes(Choice):
    """How an IMM keeps its modes (``IMMNet(modes=...)``, docs/core.md "Modes per group"), the setting ``modes``:
    ``JOINT`` (``"joint"``) one set of mode probabilities for the whole state, the IMM's; ``AXIS`` (``"axis"``) one
    per Cartesian axis (the decoupled IMM); ``CHANNEL`` (``"channel"``) one for the horizontal plane (x, y and the
    turn rate) and one for the vertical (z). ``groups``: the group of each coordinate of ``[x, w]``
    (``MODE_GROUPS``), None for ``JOINT``."""

    JOINT = "joint"
    AXIS = "axis"
    CHANNEL = "channel"

    @property
    def groups(self) -> tuple[int, ...] | None:
        return MODE_GROUPS.get(self)

    @property
    def n_groups(self) -> int | None:
        """How many groups of mode probabilities these modes keep, None for one joint set."""
        return None if self.groups is None else max(self.groups) + 1


MODE_GROUPS = {Modes.AXIS: AXIS_OF, Modes.CHANNEL: (0, 0, 0, 0, 0, 0, 1, 1, 1, 0)}
"""The group of each coordinate of ``[x, w]`` of the modes kept per group (``Modes``), each group with mode
probabilities of its own."""


def group_members(groups: tuple[int, ...]) -> list[list[int]]:
    """The coordinates of ``[x, w]`` in each group, by group: per channel ``[[0, 1, 2, 3, 4, 5, 9], [6, 7, 8]]``."""
    return [[i for i, g in enumerate(groups) if g == a] for a in range(max(groups) + 1)]


def measured_groups(groups: tuple[int, ...]) -> list[list[int]]:
    """The measured coordinates (x, y, z: the positions, ``POS``) of each group, by group: ``[[0], [1], [2]]``
    per axis, ``[[0, 1], [2]]`` per channel."""
    return [[i for i, p in enumerate(POS) if groups[p] == g] for g in range(max(groups) + 1)]


def groups_separate(F: torch.Tensor, groups: tuple[int, ...]) -> bool:
    """Whether ``F [..., n, n]`` (n 9 or 10) has no entry across ``groups`` (block diagonal per group), so that
    an IMM per group filters it exactly: per axis, CV and CA; per channel, a turn in the plane too."""
    n = F.shape[-1]
    g = torch.tensor(groups[:n])
    return not bool((F[..., g[:, None] != g[None, :]] != 0).any())


NOISE_KINDS = ("white", "wiener", "continuous")


def block_diagonal(blocks) -> torch.Tensor:
    """Block-diagonal ``[..., 3 r, 3 c]`` from the three per-axis blocks ``blocks[a] [..., r, c]`` (a sequence, or
    ``axis_blocks``' ``[3, ..., 3, 3]``): ``[..., 9, 9]`` of 3x3 blocks."""
    r, c = blocks[0].shape[-2:]
    out = blocks[0].new_zeros(*blocks[0].shape[:-2], AXES * r, AXES * c)
    for a in range(AXES):
        out[..., r * a : r * a + r, c * a : c * a + c] = blocks[a]
    return out


def axis_blocks(A: torch.Tensor) -> torch.Tensor:
    """The three per-axis 3x3 blocks of matrices ``A [..., 9, 9]`` on a new leading dimension: ``[3, ..., 3, 3]``
    (states: ``axis_states``; a batch of nine states ``[9, 9]`` would read as one matrix)."""
    if A.dim() < 2 or tuple(A.shape[-2:]) != (9, 9):
        raise ValueError(f"expected [..., 9, 9] matrices, got shape {tuple(A.shape)}")
    return torch.stack([A[..., 3 * a : 3 * a + 3, 3 * a : 3 * a + 3] for a in range(AXES)])


def axis_states(x: torch.Tensor) -> torch.Tensor:
    """The three per-axis parts (position, velocity, acceleration) of states ``x [..., 9]`` on a new leading
    dimension: ``[3, ..., 3]``."""
    if x.shape[-1] != 9:
        raise ValueError(f"expected [..., 9] states, got shape {tuple(x.shape)}")
    return x.unflatten(-1, (AXES, 3)).movedim(-2, 0)


def fits_groups(model, groups: tuple[int, ...]) -> bool:
    """Whether an IMM with modes per ``groups`` filters the motion model ``model`` (a ``MotionModel``) exactly: its
    ``F`` block diagonal per group and, for a state-dependent model (a turn estimating its rate), the turn rate in
    the group of the plane it turns in (x and y)."""
    if not groups_separate(model.F(1.0), groups):
        return False
    return not model.state_dependent or groups[POS[0]] == groups[POS[1]] == groups[RATE]


def coupling(models, groups: tuple[int, ...]) -> list[str]:
    """The names of the motion models (a ``ModelSet``, or any iterable of ``MotionModel``) that an IMM with modes per
    ``groups`` cannot filter exactly (``fits_groups``): per axis a turn; per channel none of ours."""
    return [m.name for m in models if not fits_groups(m, groups)]


def _dt(dt, dtype, device) -> torch.Tensor:
    """``dt`` as a tensor: a float gives a scalar, a tensor ``[...]`` (one interval per track) stays as it is."""
    return torch.as_tensor(dt, dtype=dtype, device=device)


def _block(rows, dt: torch.Tensor) -> torch.Tensor:
    """A per-axis block ``[..., 3, 3]`` of entries that are numbers or tensors of ``dt``'s shape."""
    full = [[torch.as_tensor(v, dtype=dt.dtype, device=dt.device).expand(dt.shape) for v in row] for row in rows]
    return torch.stack([torch.stack(row, -1) for row in full], -2)


def cv_matrix(dt, dtype=torch.float64, device=None) -> torch.Tensor:
    """Constant-velocity transition ``F_CV(dt)``, ``[9, 9]`` (``[..., 9, 9]`` for a tensor ``dt [...]``)."""
    d = _dt(dt, dtype, device)
    return block_diagonal([_block([[1.0, d, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]], d)] * AXES)


def ca_matrix(dt, dtype=torch.float64, device=None) -> torch.Tensor:
    """Constant-acceleration transition ``F_CA(dt)``, ``[9, 9]`` (``[..., 9, 9]`` for a tensor ``dt [...]``)."""
    d = _dt(dt, dtype, device)
    return block_diagonal([_block([[1.0, d, 0.5 * d * d], [0.0, 1.0, d], [0.0, 0.0, 1.0]], d)] * AXES)


def ct_matrix(turn_rate, dt, dtype=torch.float64, device=None) -> torch.Tensor:
    """Coordinated-turn transition ``F_CT(w, dt)``; a batch of turn rates ``[...]`` (and of intervals ``dt``
    broadcasting against them) gives ``[..., 9, 9]``.

    ``w`` in rad/s. At ``w -> 0`` the limits ``sin(w dt)/w -> dt`` and ``(1 - cos(w dt))/w -> 0``
    are used, so CT(0) is CV in the plane with zero acceleration.
    """
    w = torch.as_tensor(turn_rate, dtype=dtype, device=device)
    d = _dt(dt, dtype, w.device)
    w, d = torch.broadcast_tensors(w, d)
    F = cv_matrix(d, dtype=dtype, device=w.device).clone()
    for (row, col), value in zip(TURN_ENTRIES, _turn_entries(w, d, 1e-9)):
        F[..., row, col] = value
    return F


def _turn_entries(w: torch.Tensor, dt, eps: float) -> list[torch.Tensor]:
    """The entries of ``F_CT(w, dt)`` at the first 12 ``TURN_ENTRIES``, those of the plane's velocity columns::

        lx: s/w, -(1-c)/w   ly: (1-c)/w, s/w   vx: c, -s   vy: s, c   ax' = -w vy': -w s, -w c   ay' = w vx': w c, -w s

    (``s, c = sin(w dt), cos(w dt)``; ``_turn_terms``' limits for ``|w| < eps``)."""
    _, _, s, c, s_w, c_w = _turn_terms(w, dt, eps)
    return [s_w, -c_w, c_w, s_w, c, -s, s, c, -w * s, -w * c, w * c, -w * s]


def _turn_terms(w: torch.Tensor, dt, eps: float):
    """``sin(w dt)``, ``cos(w dt)``, ``sin(w dt) / w`` and ``(1 - cos(w dt)) / w`` (limits ``dt`` and 0 for
    ``|w| < eps``), ``dt`` a float or a tensor broadcasting against ``w`` (one interval per track)."""
    small = w.abs() < eps
    w_safe = torch.where(small, torch.ones_like(w), w)
    s, c = torch.sin(w * dt), torch.cos(w * dt)
    s_w = torch.where(small, torch.as_tensor(dt, dtype=w.dtype, device=w.device).expand_as(w), s / w_safe)
    c_w = torch.where(small, torch.zeros_like(w), (1.0 - c) / w_safe)
    return small, w_safe, s, c, s_w, c_w


def ct_propagate(x: torch.Tensor, turn_rate: torch.Tensor, dt) -> torch.Tensor:
    """``F_CT(w, dt) x`` for states ``x [..., 9]`` and turn rates ``w [...]`` (rad/s), in closed form.

    The same map as ``ct_matrix`` without building a matrix per state; ``w -> 0`` uses the limits.
    ``dt`` is a float or a tensor broadcasting against ``w`` (one interval per track).
    """
    w = turn_rate
    _, _, s, c, s_w, c_w = _turn_terms(w, dt, 1e-9)
    lx, vx, ly, vy = x[..., 0], x[..., 1], x[..., 3], x[..., 4]
    vx1, vy1 = c * vx - s * vy, s * vx + c * vy
    return torch.stack(
        [
            lx + s_w * vx - c_w * vy, vx1, -w * vy1,
            ly + c_w * vx + s_w * vy, vy1, w * vx1,
            x[..., 6] + dt * x[..., 7], x[..., 7], torch.zeros_like(w),
        ],
        -1,
    )


def ct_rate_derivative(x: torch.Tensor, w: torch.Tensor, dt) -> torch.Tensor:
    """``d/dw ct_propagate(x, w, dt)``, ``[..., 9]``, in closed form (``w -> 0`` by its limit); ``dt`` as
    ``ct_propagate``'s."""
    small, ws, s, c, _, _ = _turn_terms(w, dt, 1e-6)
    # d/dw sin(w dt)/w and d/dw (1 - cos(w dt))/w; limits 0 and dt^2/2 at w = 0
    ds = torch.where(small, torch.zeros_like(w), (dt * c * ws - s) / (ws * ws))
    dc = torch.where(small, (0.5 * dt * dt) * torch.ones_like(w), (dt * s * ws - (1.0 - c)) / (ws * ws))
    vx, vy = x[..., 1], x[..., 4]
    vx1, vy1 = c * vx - s * vy, s * vx + c * vy
    dvx1, dvy1 = -dt * vy1, dt * vx1
    z = torch.zeros_like(w)
    return torch.stack(
        [ds * vx - dc * vy, dvx1, -vy1 - w * dvy1, dc * vx + ds * vy, dvy1, vx1 + w * dvx1, z, z, z], -1
    )


TURN_ENTRIES = (
    (0, 1), (0, 4), (3, 1), (3, 4), (1, 1), (1, 4), (4, 1), (4, 4), (2, 1), (2, 4), (5, 1), (5, 4),
    (0, RATE), (1, RATE), (2, RATE), (3, RATE), (4, RATE), (5, RATE),
)
"""(row, column) of the entries of a turn filter's Jacobian ``d ct_propagate(x, w) / d[x, w]`` (augmented
state ``[x, w]``) that depend on ``w`` or the velocity; the rest of it is constant (``ct_jacobian``)."""


def ct_jacobian_entries(x: torch.Tensor, w: torch.Tensor, dt) -> torch.Tensor:
    """The values of ``TURN_ENTRIES`` of ``d ct_propagate(x, w) / d[x, w]``, ``[..., 18]``."""
    d = ct_rate_derivative(x, w, dt)
    return torch.stack([*_turn_entries(w, dt, 1e-6), *d[..., :6].unbind(-1)], -1)  # then the rate's column


def ct_jacobian(x: torch.Tensor, w: torch.Tensor, dt) -> torch.Tensor:
    """The full Jacobian ``d ct_propagate(x, w) / d[x, w]`` of the augmented state, ``[..., 10, 10]``: the
    constant entries (positions, the vertical CV block, ``w``'s own 1) and ``TURN_ENTRIES``."""
    dt_ = torch.as_tensor(dt, dtype=x.dtype, device=x.device).expand(w.shape)
    J = x.new_zeros(*w.shape, N_AUG, N_AUG)
    for r, c in ((0, 0), (3, 3), (6, 6), (7, 7), (RATE, RATE)):
        J[..., r, c] = 1.0
    J[..., 6, 7] = dt_
    entries = ct_jacobian_entries(x, w, dt)
    for k, (r, c) in enumerate(TURN_ENTRIES):
        J[..., r, c] = entries[..., k]
    return J


def turn_rate_of(x: torch.Tensor, min_speed: float = 1.0) -> torch.Tensor:
    """Turn rate implied by a state's horizontal velocity and acceleration, ``[...]`` (rad/s).

    In a coordinated turn the acceleration is centripetal, ``a = w x v`` (``ax = -w vy``,
    ``ay = w vx``), so ``w = (vx ay - vy ax) / (vx^2 + vy^2)``; speeds under ``min_speed`` are
    taken as ``min_speed`` (no division by zero at rest).
    """
    vx, vy, ax, ay = x[..., 1], x[..., 4], x[..., 2], x[..., 5]
    return (vx * ay - vy * ax) / (vx * vx + vy * vy).clamp_min(min_speed * min_speed)


def adaptive_ct_propagate(x: torch.Tensor, lo, hi, dt: float) -> torch.Tensor:
    """``F_CT(w, dt) x`` at the turn rate the state implies, ``w = turn_rate_of(x)`` bounded to
    ``[lo, hi]`` rad/s (floats, or tensors broadcasting against ``x[..., 0]``: one bound per expert)."""
    return ct_propagate(x, torch.clamp(turn_rate_of(x), lo, hi), dt)


def noise_gain(dt, kind: str = "white", dtype=torch.float64, device=None) -> torch.Tensor:
    """Noise gain ``G`` ``[9, 3]`` (``[..., 9, 3]`` for a tensor ``dt [...]``): per axis ``[dt^2/2, dt, 0]``
    (wiener; any other ``kind``: white, ``process_noise`` has checked it)."""
    d = _dt(dt, dtype, device)
    g = torch.stack([0.5 * d * d, d, torch.full_like(d, 1.0 if kind == "wiener" else 0.0)], -1)
    return block_diagonal([g[..., None]] * AXES)  # each axis's column g on its rows


def _singer_system(tau: float, dtype, device) -> torch.Tensor:
    """The per-axis system matrix ``A`` of the Singer model, ``d/dt [l, v, a] = A [l, v, a] + [0, 0, 1] w``:
    ``l' = v, v' = a, a' = -a / tau + w``."""
    A = torch.zeros(3, 3, dtype=dtype, device=device)
    A[0, 1] = A[1, 2] = 1.0
    A[2, 2] = -1.0 / tau
    return A


def _check_vertical(vertical) -> float:
    """A model's ``vertical``, the z axis's share of ``sigma_q``, as a float: finite and >= 0."""
    vertical = float(vertical)
    if not (math.isfinite(vertical) and vertical >= 0):
        raise ValueError(f"vertical must be finite and >= 0, got {vertical}")
    return vertical


def _check_tau(tau) -> float:
    tau = float(tau)
    if not (tau > 0 and math.isfinite(tau)):
        raise ValueError(f"the Singer model's correlation time tau must be finite and > 0 (s), got {tau}")
    return tau


def singer_block(tau: float, dt, dtype=torch.float64, device=None) -> torch.Tensor:
    """Per-axis Singer transition ``exp(A dt)`` ``[..., 3, 3]``, ``b = 1 / tau``, ``e = exp(-b dt)``::

        [[1, dt, (b dt - 1 + e) / b^2], [0, 1, (1 - e) / b], [0, 0, e]]

    computed as the matrix exponential in float64 (no cancellation for ``dt << tau``), then cast to ``dtype``; ``tau``
    as ``Singer`` has checked it."""
    d = _dt(dt, torch.float64, device)
    A = _singer_system(tau, torch.float64, device)
    return torch.linalg.matrix_exp(d[..., None, None] * A).to(dtype)


def singer_matrix(tau: float, dt, dtype=torch.float64, device=None) -> torch.Tensor:
    """Singer transition ``F(dt)``, ``[9, 9]`` (``[..., 9, 9]`` for a tensor ``dt [...]``): ``singer_block`` per axis."""
    return block_diagonal([singer_block(tau, dt, dtype=dtype, device=device)] * AXES)


def _singer_noise_closed_form(b: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Singer's ``Q / q`` in closed form (Singer 1970; Bar-Shalom, Li & Kirubarajan 8.2.3), ``b = 1 / tau``; used
    where ``b dt >= 1``, where its terms no longer cancel."""
    x = b * d
    e, e2 = torch.exp(-x), torch.exp(-2 * x)
    q11 = (1 - e2 + 2 * x + 2 * x**3 / 3 - 2 * x**2 - 4 * x * e) / (2 * b**5)
    q12 = (e2 + 1 - 2 * e + 2 * x * e - 2 * x + x**2) / (2 * b**4)
    q13 = (1 - e2 - 2 * x * e) / (2 * b**3)
    q22 = (4 * e - 3 - e2 + 2 * x) / (2 * b**3)
    q23 = (1 - e) ** 2 / (2 * b**2)
    q33 = (1 - e2) / (2 * b)
    return _block([[q11, q12, q13], [q12, q22, q23], [q13, q23, q33]], d)


def singer_noise(tau: float, dt, dtype=torch.float64, device=None) -> torch.Tensor:
    """Per-axis ``Q / q`` ``[..., 3, 3]`` of the Singer model: continuous white noise of spectral density ``q`` on
    the acceleration's rate, the acceleration reverting to zero with time constant ``tau``, integrated exactly over
    ``dt``, in float64: for ``dt <= tau`` by Van Loan's method (``exp([[-A, L L^T], [0, A^T]] dt) = [[., G], [0,
    F^T]]``, ``Q = F G``; IEEE TAC 1978), where the closed form's terms cancel (its ``q11`` is a difference of O(1)
    terms of size ``(dt / tau)^5``); beyond, by the closed form (``exp(dt / tau)`` in Van Loan's blocks would cost
    digits). ``tau -> inf`` is the CA model's white jerk; the acceleration's stationary variance is ``q tau / 2``
    (Singer, IEEE TAES 1970, with ``q = 2 sigma_m^2 / tau``); ``tau`` as ``Singer`` has checked it."""
    d = _dt(dt, torch.float64, device)
    near = d <= tau
    A = _singer_system(tau, torch.float64, device)
    C = torch.zeros(6, 6, dtype=torch.float64, device=device)
    C[:3, :3] = -A
    C[2, 5] = 1.0  # L L^T, L = [0, 0, 1]: the noise drives the acceleration
    C[3:, 3:] = A.T
    E = torch.linalg.matrix_exp(torch.where(near, d, 0.0)[..., None, None] * C)
    F = E[..., 3:, 3:].transpose(-1, -2)
    Q = F @ E[..., :3, 3:]
    Q = 0.5 * (Q + Q.transpose(-1, -2))
    far = _singer_noise_closed_form(torch.tensor(1.0 / tau, dtype=torch.float64, device=device),
                                    torch.where(near, tau, d))
    return torch.where(near[..., None, None], Q, far).to(dtype)


def continuous_noise(dt, order: int, dtype=torch.float64, device=None, tau: float | None = None) -> torch.Tensor:
    """Per-axis ``Q / q`` ``[..., 3, 3]`` of continuous white noise on derivative ``order`` (1: acceleration,
    the CV model's; 2: jerk, the CA model's: a ``MotionModel``'s ``order``), integrated exactly over ``dt`` (a float or
    a tensor ``[...]``); with ``tau`` (the Singer model's, of order 2), ``singer_noise``."""
    if tau is not None:
        return singer_noise(tau, dt, dtype=dtype, device=device)
    d = _dt(dt, dtype, device)
    if order == 1:
        rows = [[d**3 / 3, d**2 / 2, 0.0], [d**2 / 2, d, 0.0], [0.0, 0.0, 0.0]]
    else:
        rows = [[d**5 / 20, d**4 / 8, d**3 / 6], [d**4 / 8, d**3 / 3, d**2 / 2], [d**3 / 6, d**2 / 2, d]]
    return _block(rows, d)


def process_noise(sigma_q, dt, kind: str = "white", dtype=torch.float64, device=None, order: int = 1,
                  vertical: float = 1.0, tau: float | None = None) -> torch.Tensor:
    """``Q = sigma_q^2 G G^T`` (white, wiener) or ``sigma_q^2 Q_c(dt)`` (continuous, on derivative ``order``; with
    ``tau``, the Singer model's); a batch of ``sigma_q`` or of intervals ``dt`` ``[...]`` gives ``[..., 9, 9]``.
    ``vertical`` scales the z axis's ``sigma_q`` (aircraft climb and descend more gently than they turn and speed
    up; a model's, checked by its constructor)."""
    if kind not in NOISE_KINDS:
        raise ValueError(f"noise kind must be one of {', '.join(NOISE_KINDS)}, got {kind!r}")
    if tau is not None and kind != "continuous":
        raise ValueError(f"the Singer model's noise is continuous, got noise kind {kind!r}")
    # a python number checked as one: no tensor to read back (torch.compile traces a step that builds Q)
    negative = sigma_q < 0 if isinstance(sigma_q, (int, float)) else bool((torch.as_tensor(sigma_q) < 0).any())
    if negative:
        raise ValueError(f"sigma_q must be non-negative, got {sigma_q}")
    sq = torch.as_tensor(sigma_q, dtype=dtype, device=device)
    if kind == "continuous":
        Q = block_diagonal([continuous_noise(dt, order, dtype=dtype, device=device, tau=tau)] * AXES)
    else:
        G = noise_gain(dt, kind, dtype=dtype, device=device)
        Q = G @ G.transpose(-1, -2)
    if vertical != 1.0:
        Q = Q.clone()
        Q[..., 6:9, 6:9] = Q[..., 6:9, 6:9] * vertical**2
    return sq[..., None, None] ** 2 * Q


def measurement_matrix(dtype=torch.float64, device=None) -> torch.Tensor:
    """``H`` of shape ``[3, 9]`` picking the three positions."""
    return torch.eye(9, dtype=dtype, device=device)[list(POS)]
