"""The 3D-LAST generator (docs/spec.md section 2), vectorized over trajectories, float64.

Truth: ``x_t = F_{m_t}(w_t, dt_t) x_{t-1} + G(dt_t) n_t``, ``n_t ~ N(0, sigma_q^2 I3)``, ``G`` per axis
``[dt_t^2/2, dt_t, 0]`` for every mode; measurements ``z_t = H x_t + v_t``, ``v_t ~ N(0, r^2 I3)``;
with ``p_miss > 0`` each scan from the third on is missed (NaN) with that probability.

A radar's plots (``DataSpec``'s ``sigma_range``, ``sigma_azimuth``, ``sigma_elevation`` pairs, optional
``outliers``): the radar sits at the origin, and each trajectory's measurements are
:func:`immnet.data.radar.plots` of its positions (stds drawn per trajectory, polar noise, the unbiased converted
measurement) with each detection's covariance ``meas_cov [m, T, 3, 3]`` (NaN where missed) and ``r`` the RMS of
the per-axis stds of those covariances. They are drawn after everything else from a numpy generator seeded by one
draw of the block's generator (in place of the misses' draw), so that a set of the same seed holds the same truth
with or without plots; a spec without them draws nothing more.

Scan intervals: ``dt_t = dt`` at every step, or with ``dt_jitter > 0`` one draw per trajectory and step
``t >= 1``, ``dt_t ~ U[dt - dt_jitter, dt + dt_jitter]`` (drawn after the measurement noise and before
the missed detections; with ``dt_jitter = 0`` nothing is drawn, so that the bytes are those of a fixed
interval). The scan times ``t [m, T]`` (float64, ``t[:, 0] = 0``, ``t[:, k] = sum_{j<=k} dt_j``; ``k dt``
for a fixed interval) go under ``keys.TIME``; ``dt [m]`` is the nominal (mean) interval.

Label semantics (other packages rely on them):

* ``mode[t]`` is the mode whose transition produced ``states[t]`` from ``states[t-1]``; ``mode[0]``
  is the first segment's mode. ``turn_rate[t]`` is the ``w`` used at that step (0 for CV/CA).
* At the first step of a CA run the segment's acceleration is written into ``states[t-1]``
  before ``F_CA`` is applied (so ``states[t]`` carries it); if the first mode is CA it is written
  into ``x_0``, if it is a CT ``x_0`` carries the centripetal acceleration ``(-w vy, w vx, 0)``.
* Soft bounds, checked on ``states[t-1]`` before each step: outside ``bound_range_outer`` moving
  outward (inside ``bound_range_inner`` moving inward) -> CT at ``bound_turn_rate_deg`` toward
  (away from) the radar until the radial speed is beyond half the horizontal speed the other way
  (heading back by >= 30 deg); a scheduled switch during that turn does not stop it. In CA with
  horizontal speed outside ``[bound_speed_min, bound_speed_max]`` or ``|vz| > bound_vz``: one CT
  step at ``bound_turn_rate_deg`` in a random direction. After either, CV until the next
  scheduled switch.
* Hard bounds: a trajectory whose horizontal range, horizontal speed or altitude ever leaves
  ``[hard_range_min, hard_range_max]``, ``[0, hard_speed_max]``, ``[hard_alt_min, hard_alt_max]``
  is redrawn. Block ``b`` of ``m`` trajectories is simulated with spares, ``k + k//4 + 64``
  candidates for ``k = m`` slots, from the generator of ``(seed, b, 0)``; the first ``m``
  in-bounds candidates are kept in order. Should fewer pass, attempt ``a = 1, 2, ...`` does the
  same for the ``k`` slots still open with the generator of ``(seed, b, a)``.

Reproducibility: trajectories are made in blocks of ``BLOCK`` (4096); block ``b`` holds
trajectories ``[b*BLOCK, (b+1)*BLOCK)`` and draws everything from one ``torch.Generator`` seeded
from ``(seed, b, attempt)``. The bytes therefore depend on ``(seed, n, spec, single_mode)`` only,
never on how blocks are grouped into chunks or processes.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np
import torch
from tensordict import TensorDict

from immnet import keys
from immnet.data import radar
from immnet.data.spec import DataSpec
from immnet.motion import DEG, MODE_NAMES, N_MODES
from immnet.progress import progress as progress_bar

BLOCK = 4096
MAX_REDRAWS = 64
CV, CA, CTP, CTM = 0, 1, 2, 3
_DT = torch.float64


def mode_index(single_mode: str | None) -> int | None:
    """``None`` or the index of a mode name in ``MODE_NAMES``; an unknown name is a ValueError."""
    if single_mode is None:
        return None
    if single_mode not in MODE_NAMES:
        raise ValueError(f"unknown mode {single_mode!r}; valid modes: {', '.join(MODE_NAMES)}")
    return MODE_NAMES.index(single_mode)


def hashed_generator(text: str) -> torch.Generator:
    """A torch generator seeded by the SHA-256 of ``text`` (its first 8 bytes, little-endian, less one bit)."""
    digest = hashlib.sha256(text.encode()).digest()
    return torch.Generator().manual_seed(int.from_bytes(digest[:8], "little") >> 1)


def block_generator(seed: int, block: int, attempt: int = 0) -> torch.Generator:
    """The generator of one block (and redraw attempt), a hash of ``(seed, block, attempt)``."""
    return hashed_generator(f"3dlast:{int(seed)}:{int(block)}:{int(attempt)}")


def n_blocks(n: int) -> int:
    return (n + BLOCK - 1) // BLOCK


def _uniform(g, m, lo, hi, *shape):
    return lo + (hi - lo) * torch.rand(m, *shape, generator=g, dtype=_DT)


def _schedule(g, m, spec: DataSpec, single: int | None):
    """Switch steps ``[m, K]`` (sorted, every segment >= min_segment) and modes ``[m, K+1]``."""
    k = spec.n_segments - 1
    slack = spec.T - spec.n_segments * spec.min_segment
    if k > 0:
        # k distinct positions among slack+k, uniform: a uniform composition of the slack (stars and bars)
        pos = torch.rand(m, slack + k, generator=g, dtype=_DT).topk(k, dim=1).indices.sort(dim=1).values
        j = torch.arange(1, k + 1)
        switches = j * spec.min_segment + pos - (j - 1)
    else:
        switches = torch.empty(m, 0, dtype=torch.long)
    first = torch.randint(0, N_MODES, (m, 1), generator=g)
    steps = torch.randint(1, N_MODES, (m, k), generator=g)  # next mode uniform among the other three
    modes = (first + torch.cat([torch.zeros(m, 1, dtype=torch.long), steps.cumsum(1)], 1)) % N_MODES
    if single is not None:
        switches = torch.empty(m, 0, dtype=torch.long)
        modes = torch.full((m, 1), single, dtype=torch.long)
    return switches, modes


def _segment_draws(g, m, spec: DataSpec, k: int) -> list[torch.Tensor]:
    """``[m, k]`` each, in this order: the turn rate's magnitude (rad/s), the CA acceleration's horizontal magnitude,
    direction and vertical, and the sign of a speed bound's turn."""
    return [_uniform(g, m, spec.turn_rate_min_deg * DEG, spec.turn_rate_max_deg * DEG, k),
            _uniform(g, m, spec.ca_acc_h_min, spec.ca_acc_h_max, k), _uniform(g, m, 0.0, 2 * math.pi, k),
            _uniform(g, m, -spec.ca_acc_v_max, spec.ca_acc_v_max, k),
            torch.randint(0, 2, (m, k), generator=g).to(_DT) * 2 - 1]


def _out_of_bounds(rho, hs, lz, spec: DataSpec) -> torch.Tensor:
    """Where a horizontal range ``rho``, horizontal speed ``hs`` or altitude ``lz`` leaves a hard bound."""
    return ((rho < spec.hard_range_min) | (rho > spec.hard_range_max) | (hs > spec.hard_speed_max)
            | (lz < spec.hard_alt_min) | (lz > spec.hard_alt_max))


def simulate(g: torch.Generator, m: int, spec: DataSpec = DataSpec(), single: int | None = None):
    """``(trajectories, bad)``: ``m`` trajectories drawn from generator ``g``, float64, none redrawn, and the ``[m]``
    mask of those leaving a hard bound at some step (or not finite)."""
    T, dt = spec.T, spec.dt
    # --- draws, in a fixed order -----------------------------------------------------------
    rng = _uniform(g, m, spec.range_min, spec.range_max)
    az = _uniform(g, m, 0.0, 2 * math.pi)
    alt = _uniform(g, m, spec.alt_min, spec.alt_max)
    spd = _uniform(g, m, spec.speed_min, spec.speed_max)
    hdg = _uniform(g, m, 0.0, 2 * math.pi)
    vz0 = _uniform(g, m, -spec.vz_max, spec.vz_max)
    r = _uniform(g, m, spec.r_min, spec.r_max)
    switches, seg_mode = _schedule(g, m, spec, single)
    S = seg_mode.shape[1]
    draws = _segment_draws(g, m, spec, 3)
    if S > 3:  # more segments than the default: draw the extra parameters after the defaults
        draws = [torch.cat(pair, 1) for pair in zip(draws, _segment_draws(g, m, spec, S - 3))]
    seg_w, acc_mag, acc_dir, acc_z, bound_sign = draws
    q = spec.sigma_q * torch.randn(T, 3, m, generator=g, dtype=_DT)  # time-major
    v = r[:, None, None] * torch.randn(m, T, 3, generator=g, dtype=_DT)
    # scan intervals (time-major [T, m]; row 0 unused): drawn only with jitter, so that a fixed dt draws as before
    steps_dt = None
    if spec.dt_jitter > 0:
        steps_dt = _uniform(g, m, dt - spec.dt_jitter, dt + spec.dt_jitter, T).T.contiguous()
        steps_dt[0] = 0.0

    seg_w = seg_w[:, :S] * torch.where(seg_mode == CTM, -1.0, 1.0).to(_DT)
    seg_ax = (acc_mag * torch.cos(acc_dir))[:, :S]
    seg_ay = (acc_mag * torch.sin(acc_dir))[:, :S]
    seg_az = acc_z[:, :S]
    bound_sign = bound_sign[:, :S]
    w_bound = spec.bound_turn_rate_deg * DEG

    # --- state as 9 columns ------------------------------------------------------------------
    lx, ly, lz = rng * torch.cos(az), rng * torch.sin(az), alt
    vx, vy, vz = spd * torch.cos(hdg), spd * torch.sin(hdg), vz0
    zero = torch.zeros(m, dtype=_DT)
    m0, w0 = seg_mode[:, 0], torch.where(seg_mode[:, 0] >= CTP, seg_w[:, 0], zero)
    is_ca = m0 == CA
    ax = torch.where(is_ca, seg_ax[:, 0], -w0 * vy)
    ay = torch.where(is_ca, seg_ay[:, 0], w0 * vx)
    azz = torch.where(is_ca, seg_az[:, 0], zero)

    # time-major buffers: each step writes contiguous rows; transposed once at the end
    states = torch.empty(T, m, 9, dtype=_DT)
    mode = torch.empty(T, m, dtype=torch.long)
    turn = torch.empty(T, m, dtype=_DT)
    torch.stack([lx, vx, ax, ly, vy, ay, lz, vz, azz], 1, out=states[0])
    mode[0], turn[0] = m0, w0

    # override: 0 none, 1 outer-range turn, 2 inner-range turn, 3 CV until the next switch
    ovr = torch.zeros(m, dtype=torch.long)
    ovr_w = zero.clone()
    prev_mode = m0
    bad = torch.zeros(m, dtype=torch.bool)
    clear_share = math.sin(spec.bound_clear_heading_deg * DEG)  # radial share beyond sin(30 deg) = 1/2
    for t in range(1, T):
        dt = spec.dt if steps_dt is None else steps_dt[t]  # this step's interval: a float, or [m]
        half_dt2 = 0.5 * dt * dt
        seg = (switches <= t).sum(1)  # switches [m, 0] (one segment): 0 and False throughout
        new_seg = (switches == t).any(1)
        ovr = torch.where(new_seg & (ovr == 3), 0, ovr)
        segi = seg[:, None]
        smode = seg_mode.gather(1, segi)[:, 0]
        # soft bounds on x_{t-1}
        rho = torch.sqrt(lx * lx + ly * ly)
        hs = torch.sqrt(vx * vx + vy * vy)
        vr = (lx * vx + ly * vy) / rho
        cross_sign = torch.where(lx * vy - ly * vx >= 0, 1.0, -1.0).to(_DT)
        bad |= _out_of_bounds(rho, hs, lz, spec)
        free = (ovr == 0) | (ovr == 3)
        outer = free & (rho > spec.bound_range_outer) & (vr > 0)
        inner = free & (rho < spec.bound_range_inner) & (vr < 0)
        ovr = torch.where(outer, 1, torch.where(inner, 2, ovr))
        ovr_w = torch.where(outer, cross_sign * w_bound, torch.where(inner, -cross_sign * w_bound, ovr_w))
        cleared = ((ovr == 1) & (vr < -clear_share * hs)) | ((ovr == 2) & (vr > clear_share * hs))
        ovr = torch.where(cleared, 3, ovr)
        speed_bad = (ovr == 0) & (smode == CA) & (
            (hs < spec.bound_speed_min) | (hs > spec.bound_speed_max) | (vz.abs() > spec.bound_vz)
        )
        sb_w = bound_sign.gather(1, segi)[:, 0] * w_bound
        # the mode and turn rate applied at this step
        ranged = (ovr == 1) | (ovr == 2)
        mt = torch.where(ovr == 0, smode, CV)
        w = torch.where(ovr == 0, torch.where(smode >= CTP, seg_w.gather(1, segi)[:, 0], zero), zero)
        w = torch.where(ranged, ovr_w, torch.where(speed_bad, sb_w, w))
        mt = torch.where(ranged | speed_bad, torch.where(w > 0, CTP, CTM), mt)
        ovr = torch.where(speed_bad, 3, ovr)
        # CA: write the segment's acceleration at the first step of a run
        use_ca = mt == CA
        start = use_ca & (new_seg | (prev_mode != CA))
        ax = torch.where(start, seg_ax.gather(1, segi)[:, 0], ax)
        ay = torch.where(start, seg_ay.gather(1, segi)[:, 0], ay)
        azz = torch.where(start, seg_az.gather(1, segi)[:, 0], azz)
        # closed-form transition; CV and CA are CT's w -> 0 limit plus the CA acceleration terms
        is_ct = mt >= CTP
        wdt = w * dt
        s, c = torch.sin(wdt), torch.cos(wdt)
        w_safe = torch.where(is_ct, w, 1.0)
        s_w = torch.where(is_ct, s / w_safe, dt)
        c_w = torch.where(is_ct, (1.0 - c) / w_safe, 0.0)
        ka = use_ca.to(_DT)
        nlx = lx + s_w * vx - c_w * vy + ka * half_dt2 * ax
        nly = ly + c_w * vx + s_w * vy + ka * half_dt2 * ay
        nvx = c * vx - s * vy + ka * dt * ax
        nvy = s * vx + c * vy + ka * dt * ay
        nlz = lz + dt * vz + ka * half_dt2 * azz
        nvz = vz + dt * ka * azz
        ax = torch.where(is_ct, -w * nvy, ka * ax)
        ay = torch.where(is_ct, w * nvx, ka * ay)
        azz = ka * azz
        qt = q[t]
        lx, ly, lz = nlx + half_dt2 * qt[0], nly + half_dt2 * qt[1], nlz + half_dt2 * qt[2]
        vx, vy, vz = nvx + dt * qt[0], nvy + dt * qt[1], nvz + dt * qt[2]
        torch.stack([lx, vx, ax, ly, vy, ay, lz, vz, azz], 1, out=states[t])
        mode[t], turn[t] = mt, w
        prev_mode = mt

    states = states.transpose(0, 1).contiguous()
    mode, turn = mode.T.contiguous(), turn.T.contiguous()
    meas = states[..., [0, 3, 6]] + v
    cov = None
    if spec.plots:  # the radar's plots replace meas and r; drawn last from a numpy generator seeded from g
        plot_rng = np.random.default_rng(int(torch.randint(0, 2**62, (1,), generator=g)))
        z, r_plot, c = radar.plots(states[..., [0, 3, 6]].numpy(), *spec.plot_stds(), spec.p_miss, spec.outliers,
                                   spec.outlier_scale, plot_rng)
        meas, r, cov = torch.from_numpy(z), torch.from_numpy(r_plot), torch.from_numpy(c)
    elif spec.p_miss > 0:  # drawn last, so that p_miss = 0 leaves every other draw as it was
        missed = torch.rand(m, T, generator=g, dtype=_DT) < spec.p_miss
        missed[:, :2] = False  # a track starts from two detections
        meas[missed] = float("nan")
    rho, hs = torch.hypot(lx, ly), torch.hypot(vx, vy)  # the last state
    bad |= _out_of_bounds(rho, hs, lz, spec) | ~torch.isfinite(lx + ly + lz + vx + vy + vz)
    if steps_dt is None:
        times = (torch.arange(T, dtype=_DT) * spec.dt).expand(m, T).contiguous()
    else:
        times = steps_dt.T.cumsum(1)  # row 0 is 0: t[:, 0] = 0
    td = TensorDict(
        {keys.STATES: states, keys.MEASUREMENTS: meas, keys.MODE: mode, keys.TURN_RATE: turn,
         keys.R: r, keys.DT: torch.full((m,), float(spec.dt), dtype=_DT), keys.TIME: times},
        batch_size=[m],
    )
    if cov is not None:
        td.set(keys.MEAS_COV, cov)
    return td, bad


def generate_block(seed: int, block: int, n: int, spec: DataSpec = DataSpec(), single_mode=None) -> TensorDict:
    """Block ``block`` of a data set of ``n`` trajectories: trajectories ``[block*BLOCK, ...)``."""
    single = mode_index(single_mode)
    m = min(BLOCK, n - block * BLOCK)
    if m <= 0:
        raise ValueError(f"block {block} is past the end of a data set of {n} trajectories")
    parts, todo, attempt = [], m, 0
    while todo:
        if attempt > MAX_REDRAWS:
            raise RuntimeError(
                f"{todo} trajectories still leave the hard bounds after {MAX_REDRAWS} redraws; "
                "check the DataSpec bounds"
            )
        # spare trajectories so that one attempt nearly always suffices; the first in-bounds ones are kept
        sub, bad = simulate(block_generator(seed, block, attempt), todo + todo // 4 + 64, spec, single)
        good = (~bad).nonzero()[:, 0][:todo]
        parts.append(sub[good])
        todo -= len(good)
        attempt += 1
    return parts[0] if len(parts) == 1 else torch.cat(parts, 0)


def generate(n: int, seed: int, spec: DataSpec = DataSpec(), single_mode: str | None = None,
             progress: bool = False) -> TensorDict:
    """``n`` 3D-LAST trajectories from ``seed``: a float64 ``TensorDict`` of batch ``[n]`` (see module doc).

    ``single_mode`` in ``MODE_NAMES`` gives one-segment trajectories of that mode (soft bounds
    still apply; the labels say what was used).
    """
    n = int(n)
    if n <= 0:
        raise ValueError(f"n must be a positive number of trajectories, got {n}")
    mode_index(single_mode)  # validates the name
    blocks = progress_bar(range(n_blocks(n)), desc="3D-LAST", unit="block", disable=not progress)
    return torch.cat([generate_block(seed, b, n, spec, single_mode) for b in blocks], 0)
