"""Many targets from unlabelled plots: gating, association (GNN or JPDA), two-point initiation, confirmation by a track
score (or M of N), coasting and deletion around a batched per-track filter (docs/multi-target.md, "The tracker").

    tracker = MultiTargetTracker(r=50.0)                         # the IMM tuned at the scan interval, or a filter
                                                                  # by name ("real-imm-5s"; a network: "radar-5s")
    for t, plots in scans:                                        # plots [N, 3] ENU (m); R [N, 3, 3] optional
        for rep in tracker.step(t, plots):                        # the confirmed tracks
            rep.track_id, rep.state, rep.cov, rep.updated

One scan, for every live track at once:

1. the filter predicts every track to the scan (one tensor step) and gives each track's predicted position and its
   covariance ``S_i = H P_i H^T`` (an IMM's moment-matched prior over its modes; a filter with a measurement noise
   of its own, ``plot_noise`` False, includes it, and the gate adds no plot's ``R_j`` below);
2. gating: a k-d tree of the plots gives the plots inside a ball that holds each track's gate; on those pairs only,
   ``d^2 = nu^T (S_i + R_j)^{-1} nu <= chi2_3(gate)`` (``immnet.imm.kalman.inv3``), and the pair's log-likelihood
   ``log N(nu; 0, S_i + R_j)`` (``gaussian_loglik``);
3. association, confirmed tracks first: GNN, an optimal assignment (``linear_sum_assignment``) of cost
   ``-log N`` per cluster of tracks and plots linked by gated pairs, the most pairs first; or JPDA, each cluster's
   association probabilities over its joint events. Tentative tracks then take, by GNN, the plots the confirmed
   tracks left (not assigned; under JPDA, outside their gates);
4. the filter updates every track at once with its plot (a NaN row where none: it coasts on its prediction) or,
   under JPDA, with the mixture of its gated plots (``TrackFilter.update_mixture``);
5. initiation: a plot nobody took pairs with a seed, an unpaired plot of an earlier scan, whose distance fits a
   speed of at most ``max_speed`` (plus ``sigma`` measurement standard deviations), by an assignment over the pairs
   a k-d tree finds; a pair starts a tentative track (two-point differencing); the plots left over become seeds;
6. confirmation by a sequential track score (``TrackScore``: each plot's likelihood against the clutter density
   estimated from the plots; confirmed at a threshold, dropped at another or after a window), or after M hits within
   the first N scans (``confirm=(M, N)``; a tentative track that can no longer reach M is dropped); a confirmed
   track is deleted after ``delete_after`` consecutive misses spanning at
   least ``min_coast`` seconds since its last plot, any track once its position standard deviation
   ``sqrt(tr P_pos)`` exceeds ``max_pos_std`` or, told the radar's ``Cover``, at a miss while its estimate lies
   outside it.

Every step of gating, association and initiation touches only the pairs inside a gate (the trees find them), so a
scan costs about ``N log N + K log N + pairs``: clutter far from every track adds plots, not plots times tracks.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.stats import chi2

from immnet.data.radar import covered
from immnet.filters.imm import ACC_STD, VEL_STD
from immnet.filters.registry import MULTI_TARGET_BANDS, MULTI_TARGET_FILTER
from immnet.imm.interaction import combine, mix, mixing_weights, mode_update, moment_match, transition_matrix
from immnet.imm.kalman import (check_robust, check_vz_std, gaussian_loglik, inv3, predict, quadratic, start_state,
                               update, vertical_speed_prior)
from immnet.motion import AXES, AXIS_OF, CV, ModelSet, Modes, coupling
from immnet.motion.models import axis_blocks, block_diagonal

GROUPS = (Modes.JOINT, Modes.AXIS)
"""The modes a multi-target IMM keeps (``IMMFilter(groups=...)``)."""


# --- the per-track filter ------------------------------------------------------------------------------------------

class TrackFilter:
    """What the multi-target tracker asks of a filter: a batch of ``K`` live tracks (rows, in order), stepped
    together. ``start`` appends tracks at the end (from a plot, or a pair: ``z_prev``, ``R_prev`` ``dt`` earlier,
    with ``vz_std`` the prior std of the vertical speed and ``p_cv`` the first probability of the constant-velocity
    mode, where the filter takes them); ``predict`` moves every track to
    the next scan and gives its predicted position ``[K, 3]`` and that position's covariance ``H P H^T`` ``[K, 3, 3]``
    (without the measurement noise, which the tracker adds per plot); ``update`` takes one plot per track (a NaN row:
    missed, the posterior is the prior); ``update_mixture`` (JPDA) the gated pairs' plots with their association
    probabilities; ``drop(keep)`` keeps the rows of ``keep [K]``; ``state()`` gives the combined estimate ``x [K, 9]``,
    ``P [K, 9, 9]`` in the layout ``[x, vx, ax, y, vy, ay, z, vz, az]``. Arrays in and out are numpy float64.

    ``r``: the measurement std (m) the filter assumes where plots come without covariances (None: it assumes
    none); ``name``: what it is, for messages; ``plot_noise``: the filter measures with each plot's ``R``, which the
    gate adds to the predicted covariance (False: the filter has its own measurement noise, already in the covariance
    ``predict`` gives); ``no_mixture``: None, or why the filter has no mixture update (JPDA is then refused, with
    this line)."""

    r: float | None = None
    name: str = "filter"
    plot_noise: bool = True
    no_mixture: str | None = None

    def __len__(self) -> int:  # pragma: no cover - interface
        raise NotImplementedError

    def start(self, z, R, z_prev=None, R_prev=None, dt=None, vz_std=None,
              p_cv=None) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def predict(self, dt: float):  # pragma: no cover - interface
        raise NotImplementedError

    def update(self, z, R) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def update_mixture(self, track, z, R, beta, beta0) -> None:
        raise NotImplementedError(f"{self.name} has no mixture update: JPDA needs one (use associator='gnn')")

    def check_interval(self, dt: float) -> None:
        """A ValueError unless the filter takes a scan ``dt`` seconds after the last (the tracker asks before it
        changes anything; the model-based filters take any interval)."""

    def drop(self, keep) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def state(self):  # pragma: no cover - interface
        raise NotImplementedError

    @staticmethod
    def by_name(name: str, r: float | None = None) -> "TrackFilter":
        """The filter named ``name``: a shipped network (``immnet.checkpoints.SHIPPED``: ``radar-5s``, ``real-5s``,
        ...; ``immnet.tracking.network_filter.NetworkFilter``, built from its class path as a method config's class
        is, so that this layer imports nothing of ``immnet.tracking``), a model-based method (``from_method``) or
        ``MULTI_TARGET_FILTER``, the IMM tuned at the scan interval (``ByInterval``). ``r``: the measurement std to
        assume where plots come without covariances (a method's; a network assumes none)."""
        from immnet.checkpoints import BANK, BANK_MEMBERS, SHIPPED

        if name == BANK:
            raise ValueError(f"{name} is several networks weighed per track, not one: the multi-target tracker's "
                             f"network filters are the shipped networks by name ({', '.join(BANK_MEMBERS)}, ...)")
        if name == MULTI_TARGET_FILTER:
            return ByInterval(r=r)
        if name in SHIPPED:
            from immnet.config import import_class

            return import_class(NETWORK_FILTER, TrackFilter).pretrained(name)
        return TrackFilter.from_method(name, r)

    @staticmethod
    def from_method(name: str, r: float | None = None) -> "IMMFilter":
        """The filter of the method ``name`` (``configs/methods/<name>.yaml``): a model-based IMM (``IMMTracker``
        with joint modes, ``PerAxisIMMTracker``) or a Kalman filter (``KalmanFilterTracker``), with its model set,
        process noise, transition matrix, initial mode probabilities and robust update. ``r``: the measurement std to
        assume where plots come without covariances; None: the method's own ``r`` where it is a number (``r: data``
        assumes none). A method's re-acquisition is not taken: the multi-target tracker starts and deletes tracks."""
        from immnet.filters.methods import build_method

        return TrackFilter.of_method(build_method(name), name, r)

    @staticmethod
    def of_method(method, name: str, r: float | None = None) -> "IMMFilter":
        """``from_method`` of a method already built (``immnet tune --scenes`` scores each setting so)."""
        from immnet.filters.per_axis import PerAxisIMMTracker
        from immnet.filters.trackers import IMMTracker
        from immnet.imm.measurement import Isotropic

        own_r = method.measurement.r if isinstance(getattr(method, "measurement", None), Isotropic) else None
        common = {"r": own_r if r is None else r, "name": name, "robust": getattr(method, "robust", None)}
        if isinstance(method, PerAxisIMMTracker):
            return IMMFilter(method.model_set, method.sigma_q, method.Pi, groups=Modes.AXIS, **common)
        if isinstance(method, IMMTracker):
            if method.modes is not Modes.JOINT:
                raise ValueError(f"{name}: an IMM with modes per {method.modes} is not a multi-target filter "
                                 f"(joint modes or a per-axis IMM are)")
            return IMMFilter(method.model_set, method.sigma_q, method.Pi, mu0=method.mu0, **common)
        raise ValueError(f"{name} is a {type(method).__name__}: the multi-target tracker's filters are the model-based "
                         f"IMMs and Kalman filters (IMMTracker, PerAxisIMMTracker, KalmanFilterTracker) and the "
                         f"shipped networks by their weights' name (radar-5s, real-5s, ...)")


NETWORK_FILTER = "immnet.tracking.network_filter.NetworkFilter"
"""The class of a shipped network as a per-track filter (``TrackFilter.by_name``)."""


def _t(a) -> torch.Tensor:
    return torch.from_numpy(np.array(a, dtype=np.float64))


class IMMFilter(TrackFilter):
    """A model-based IMM over a model set, for a batch of tracks: ``groups="joint"`` one set of mode probabilities
    per track (``IMMTracker``), ``"axis"`` one per Cartesian axis (``PerAxisIMMTracker``: three independent IMMs over
    ``[l, v, a]``, each measuring its coordinate with the plot covariance's diagonal element; models must be block
    diagonal per axis). One model is a Kalman filter. The stages are ``immnet.imm``'s (``mixing_weights``, ``mix``,
    ``predict``, ``update``, ``mode_update``, ``combine``), batched over tracks, axes and models: a step is one
    tensor expression for every track.

    ``sigma_q``: the process noise, one value or one per model; ``p_stay``: the staying probability or a transition
    matrix ``[M, M]``; ``mu0``: the initial mode probabilities (uniform). A one-point start (``start(z, R)``) is the
    single-target IMMs' (``immnet.filters.imm.initial_state``: velocity std ``vel_std``, acceleration std
    ``acc_std``); a two-point start (``start(z, R, z_prev, R_prev, dt)``) differences the plots: velocity
    ``(z - z_prev) / dt`` with covariance ``(R + R_prev) / dt^2`` plus what an acceleration of std ``acc_std``
    adds over the interval (``acc_std^2 dt^2 / 4``, the average velocity being the one at mid-interval), then, given
    ``vz_std``, fused with the prior ``vz ~ N(0, vz_std^2)`` (an update measuring ``vz`` as 0); given ``p_cv``, a new
    track's mode probabilities are ``p_cv`` on the constant-velocity models and the rest spread evenly over the others
    (``mu0`` otherwise, and where the models are all or none constant-velocity ones). ``robust``:
    Huber's ``k`` of the update (``immnet.imm.kalman``: an isolated far plot's weight falls beyond ``k`` standard
    deviations of its innovation; with JPDA a track's plot is far when every plot in its gate is), None the plain
    update."""

    def __init__(self, model_set, sigma_q, p_stay=0.98, mu0=None, groups: Modes | str = Modes.JOINT,
                 r: float | None = None, vel_std: float = VEL_STD, acc_std: float = ACC_STD, name: str = "imm",
                 robust: float | None = None):
        if (kind := Modes.lookup(groups)) not in GROUPS:  # a Modes or its spelling, one of GROUPS
            raise ValueError(f"groups must be one of {', '.join(GROUPS)}, got {groups!r}")
        self.model_set = ModelSet.from_config(model_set)
        self.M = M = len(self.model_set)
        if any(m.state_dependent for m in self.model_set):
            raise ValueError(f"{name}: the IMM needs a constant F per model")
        if kind is Modes.AXIS and (moving := coupling(self.model_set, AXIS_OF)):
            raise ValueError(f"{name}: a per-axis IMM needs models block diagonal per axis; {moving} couple the axes")
        self.sigma_q = [float(v) for v in sigma_q] if isinstance(sigma_q, (list, tuple)) else float(sigma_q)
        self.Pi = transition_matrix(p_stay, M) if not isinstance(p_stay, torch.Tensor) else p_stay.double()
        self.mu0 = torch.full((M,), 1.0 / M, dtype=torch.float64) if mu0 is None else _t(mu0).reshape(M)
        joint = kind is Modes.JOINT
        self.groups, self.G, self.d = kind, (1 if joint else AXES), (9 if joint else 3)
        self.r, self.name = (None if r is None else float(r)), name
        self.robust = check_robust(robust)
        self.vel_std, self.acc_std = float(vel_std), float(acc_std)
        f64 = torch.float64
        self.x = torch.zeros(0, self.G, M, self.d, dtype=f64)
        self.P = torch.zeros(0, self.G, M, self.d, self.d, dtype=f64)
        self.mu = torch.zeros(0, self.G, M, dtype=f64)
        self.spare = torch.zeros(0, self.G, 1, dtype=torch.bool)  # the robust update's (immnet.imm.kalman)
        self._cache = (None, None)
        self._H = torch.tensor([[1.0, 0.0, 0.0]], dtype=f64)

    def __len__(self) -> int:
        return self.x.shape[0]

    def __repr__(self) -> str:
        return f"IMMFilter({self.name}: {self.model_set}, modes {self.groups}, {len(self)} tracks)"

    # the 9-D state to the filter's groups and back
    def _split(self, A: torch.Tensor) -> torch.Tensor:
        """``[K, 9]`` or ``[K, 9, 9]`` -> ``[K, G, d]`` or ``[K, G, d, d]`` (the axis blocks; joint: one group)."""
        if self.groups is Modes.JOINT:
            return A[:, None]
        return axis_blocks(A).movedim(0, 1) if A.dim() == 3 else A.reshape(len(A), AXES, 3)

    def _join(self, x: torch.Tensor, P: torch.Tensor):
        """``[K, G, d]``, ``[K, G, d, d]`` -> ``[K, 9]``, ``[K, 9, 9]`` (axis blocks on the diagonal)."""
        if self.groups is Modes.JOINT:
            return x[:, 0], P[:, 0]
        return x.reshape(len(x), 9), block_diagonal(P.unbind(1))

    def _matrices(self, dt: float):
        if self._cache[0] != dt:
            F = self.model_set.F(dt, dtype=torch.float64)  # [M, 9, 9]
            Q = self.model_set.Q(self.sigma_q, dt, dtype=torch.float64)
            joint = self.groups is Modes.JOINT
            self._cache = (dt, tuple(A[None] if joint else axis_blocks(A) for A in (F, Q)))  # [G, M, d, d]
        return self._cache[1]

    @torch.no_grad()
    def start(self, z, R, z_prev=None, R_prev=None, dt=None, vz_std=None, p_cv=None) -> None:
        z, R = _t(z).reshape(-1, 3), _t(R).reshape(-1, 3, 3)
        k = z.shape[0]
        if k == 0:
            return
        x0, P0 = start_state(z, R, self.vel_std, self.acc_std)  # one point: the single-target IMMs' start
        if z_prev is not None:  # two: the differenced velocity
            pos, vel, acc = slice(0, 9, 3), slice(1, 9, 3), slice(2, 9, 3)
            eye = torch.eye(3, dtype=torch.float64)
            qa = self.acc_std**2
            zp, Rp = _t(z_prev).reshape(-1, 3), _t(R_prev).reshape(-1, 3, 3)
            dt = _t(dt).reshape(-1).expand(k)[:, None, None]
            x0[:, vel] = (z - zp) / dt[..., 0]
            P0[:, vel, vel] = (R + Rp) / dt**2 + qa * dt**2 / 4 * eye
            for a, b, cross in ((pos, vel, R / dt), (vel, acc, qa * dt / 2 * eye)):  # and their transposes
                P0[:, a, b] = P0[:, b, a] = cross
            if vz_std is not None:
                x0, P0 = vertical_speed_prior(x0, P0, vz_std)
        G, M, d = self.G, self.M, self.d
        self.x = torch.cat([self.x, self._split(x0)[:, :, None].expand(k, G, M, d)])
        self.P = torch.cat([self.P, self._split(P0)[:, :, None].expand(k, G, M, d, d)])
        self.mu = torch.cat([self.mu, (self.mu0 if p_cv is None else self.cv_weighted(p_cv)).expand(k, G, M)])
        self.spare = torch.cat([self.spare, torch.zeros(k, G, 1, dtype=torch.bool)])

    def cv_weighted(self, p_cv: float) -> torch.Tensor:
        """Mode probabilities ``[M]``: ``p_cv`` spread evenly over the constant-velocity models, the rest over the
        others; ``mu0`` where the filter has no constant-velocity model or only such models (a Kalman filter)."""
        cv = self.model_set.modes.to(torch.long) == CV
        if not bool(cv.any()) or bool(cv.all()):
            return self.mu0
        n = cv.sum().to(torch.float64)
        return torch.where(cv, p_cv / n, (1.0 - p_cv) / (len(cv) - n))

    @torch.no_grad()
    def predict(self, dt: float):
        K, G, M, d = len(self), self.G, self.M, self.d
        if K == 0:
            return np.zeros((0, 3)), np.zeros((0, 3, 3))
        F, Q = self._matrices(float(dt))
        w = mixing_weights(self.mu.reshape(K * G, M), self.Pi)
        x0, P0 = mix(w, self.x.reshape(K * G, M, d), self.P.reshape(K * G, M, d, d))
        self.x, self.P = predict(x0.view(K, G, M, d), P0.view(K, G, M, d, d), F, Q)
        self.mu = self.mu @ self.Pi  # the predicted mode probabilities (the update's prior)
        xc, Pc = self._combined()
        if self.groups is Modes.JOINT:
            return xc[:, 0, 0::3].numpy(), Pc[:, 0, 0::3, 0::3].numpy()
        return xc[..., 0].numpy(), torch.diag_embed(Pc[..., 0, 0]).numpy()

    def _combined(self):
        """Each group's moment-matched estimate over the modes, ``[K, G, d]`` and ``[K, G, d, d]``."""
        K, G, M, d = len(self), self.G, self.M, self.d
        xc, Pc = combine(self.x.reshape(K * G, M, d), self.P.reshape(K * G, M, d, d), self.mu.reshape(K * G, M))
        return xc.view(K, G, d), Pc.view(K, G, d, d)

    def _measure(self, z, R):
        """A plot per row, ``z [K, 3]``, ``R [K, 3, 3]`` (numpy), as the filter's groups measure it: ``(z [K, G, 1, m],
        R [K, G, 1, m, m], H)`` (per axis: the coordinate and ``R``'s diagonal element)."""
        z, R = _t(z).reshape(-1, 3), _t(R).reshape(-1, 3, 3)
        if self.groups is Modes.JOINT:
            return z[:, None, None, :], R[:, None, None], None
        return z[..., None, None], torch.diagonal(R, dim1=-2, dim2=-1)[..., None, None, None], self._H

    @torch.no_grad()
    def update(self, z, R) -> None:
        if len(self) == 0:
            return
        zm, Rm, H = self._measure(z, R)
        x, P, ll, *after = update(self.x, self.P, zm, H, Rm, self.robust, self._spare())
        self.x, self.P, self.mu = x, P, mode_update(torch.log(self.mu), ll)
        self.spare = after[0] if after else self.spare

    def _spare(self, rows=None):
        """The robust update's ``spare`` of every track (of ``rows``), None without a robust update."""
        return None if self.robust is None else (self.spare if rows is None else self.spare[rows])

    @torch.no_grad()
    def update_mixture(self, track, z, R, beta, beta0) -> None:
        """JPDA: the gated pairs, ``track [P]`` (the track's row), ``z [P, 3]``, ``R [P, 3, 3]`` (the plot), ``beta [P]``
        (the pair's association probability), and ``beta0 [K]`` (no plot is the track's). Each mode's posterior is the
        mixture over the track's hypotheses (no plot: the prior) weighted by ``beta_h P(mode | h)`` (the mode's
        likelihood under ``h``), moment-matched (``moment_match``, a pair at a time, summed per track); the mode
        probabilities are ``sum_h beta_h P(mode | h)``. Its cost grows with the pairs, not tracks times plots."""
        K, G, M, d = len(self), self.G, self.M, self.d
        if K == 0:
            return
        track = torch.from_numpy(np.asarray(track, dtype=np.int64))
        beta, beta0 = _t(beta), _t(beta0)
        zm, Rm, H = self._measure(z, R)
        xh, Ph, ll, *after = update(self.x[track], self.P[track], zm, H, Rm, self.robust, self._spare(track))
        if after:  # far: a track with plots in its gate, each beyond k of every filter
            pairs = torch.zeros(K, G, 1, dtype=torch.long).index_add(0, track, torch.ones_like(after[0], dtype=torch.long))
            near = torch.zeros(K, G, 1, dtype=torch.long).index_add(0, track, (~after[0]).long())
            self.spare = torch.where(pairs > 0, near == 0, self.spare)
        W = beta[:, None, None] * torch.softmax(torch.log(self.mu[track]) + ll, -1)  # beta_h P(mode | h)
        W0 = beta0[:, None, None] * self.mu
        mu = W0.index_add(0, track, W)  # [K, G, M]
        scale = mu.clamp_min(torch.finfo(mu.dtype).tiny)
        x = (W0[..., None] * self.x).index_add(0, track, W[..., None] * xh) / scale[..., None]

        def spread(w, xs, Ps, xf):  # w (P + (x - xf)(x - xf)^T) per row, one component each
            rows = w.numel()
            return moment_match(w.reshape(rows, 1, 1, 1), xs.reshape(rows, 1, d), xf.reshape(rows, d),
                                Ps.reshape(rows, 1, d, d)).view(-1, G, M, d, d)

        P = spread(W0, self.x, self.P, x).index_add(0, track, spread(W, xh, Ph, x[track]))
        self.x, self.P, self.mu = x, P / scale[..., None, None], mu

    def drop(self, keep) -> None:
        keep = torch.as_tensor(np.asarray(keep, dtype=bool))
        self.x, self.P, self.mu, self.spare = self.x[keep], self.P[keep], self.mu[keep], self.spare[keep]

    @torch.no_grad()
    def state(self):
        if len(self) == 0:
            return np.zeros((0, 9)), np.zeros((0, 9, 9))
        x, P = self._join(*self._combined())
        return x.numpy(), P.numpy()

    def mode_probs(self) -> np.ndarray:
        """The mode probabilities ``[K, G, M]`` (after ``predict``: the predicted ones)."""
        return self.mu.numpy()

    def data_mode_probs(self) -> np.ndarray | None:
        """The probabilities of the data modes CV, CA, CT+, CT- ``[K, 4]`` (each model's summed into the mode it
        stands for, as the single-target IMMs report them); None for modes per axis (an axis has none of the data
        modes) and for one model (a Kalman filter: no mode to weigh)."""
        if self.groups is not Modes.JOINT or self.M == 1:
            return None
        from immnet.filters.base import data_mode_probs

        return data_mode_probs(self.mu[:, 0], self.model_set.modes).numpy()


class ByInterval(TrackFilter):
    """The IMM tuned at the radar's scan interval (``immnet.filters.registry.MULTI_TARGET_BANDS``: the first band
    whose longest interval holds it), chosen by ``choose(dt)``: by the caller who knows the scan interval (``immnet
    track``: the median of its CSV's), else at the first interval it is given (the tracker's second scan, before any
    track starts): ``check_interval``, or a ``start``'s or ``predict``'s ``dt``. It is then that method's filter
    (``TrackFilter.from_method``, each band's built here, so that the scan that chooses costs no more than another);
    ``chosen`` names it (None before). ``r``: as ``from_method``'s."""

    def __init__(self, bands=MULTI_TARGET_BANDS, r: float | None = None):
        self.r, self.name, self.chosen = r, MULTI_TARGET_FILTER, None
        self.bands = [(float(longest), name, TrackFilter.from_method(name, r)) for longest, name in bands]
        self._filter = None

    def choose(self, dt) -> TrackFilter:
        """The filter for scans ``dt`` s apart (its first element where an array), chosen once: later calls return
        it whatever their ``dt``."""
        if self._filter is None:
            dt = float(np.asarray(dt, dtype=np.float64).reshape(-1)[0])
            _, self.chosen, self._filter = next(band for band in self.bands if dt <= band[0])
        return self._filter

    def __len__(self) -> int:
        return 0 if self._filter is None else len(self._filter)

    def __repr__(self) -> str:
        return f"ByInterval({self.chosen or 'not chosen yet'})"

    def check_interval(self, dt: float) -> None:
        self.choose(dt).check_interval(dt)

    def start(self, z, R, z_prev=None, R_prev=None, dt=None, vz_std=None, p_cv=None) -> None:
        if self._filter is None and dt is None:
            raise ValueError(f"{self.name} chooses its filter by the scan interval: its first start needs dt")
        self.choose(dt).start(z, R, z_prev, R_prev, dt, vz_std, p_cv)

    def predict(self, dt: float):
        return self.choose(dt).predict(dt)

    def update(self, z, R) -> None:
        self._filter.update(z, R)

    def update_mixture(self, track, z, R, beta, beta0) -> None:
        self._filter.update_mixture(track, z, R, beta, beta0)

    def drop(self, keep) -> None:
        self._filter.drop(keep)

    def state(self):
        return (np.zeros((0, 9)), np.zeros((0, 9, 9))) if self._filter is None else self._filter.state()

    def data_mode_probs(self) -> np.ndarray | None:
        return None if self._filter is None else self._filter.data_mode_probs()


# --- association ---------------------------------------------------------------------------------------------------

def gate_pairs(z_pred: np.ndarray, S: np.ndarray, plots: np.ndarray, R: np.ndarray, threshold: float,
               tree: cKDTree | None = None):
    """The gated (track, plot) pairs: ``nu^T (S_i + R_j)^{-1} nu <= threshold``, ``nu = plot_j - z_pred_i``. A k-d tree
    of the plots gives the candidates, the plots inside a ball of radius ``sqrt(threshold (tr S_i + max_j tr R_j))``,
    which holds the gate's ellipsoid (its largest semi-axis is ``sqrt(threshold lambda_max)``, ``lambda_max <=``
    the trace); the test itself runs on those alone. Returns ``(track [P], plot [P], loglik [P])`` with
    ``loglik = log N(nu; 0, S_i + R_j)``."""
    K, N = len(z_pred), len(plots)
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if K == 0 or N == 0:
        return empty
    tree = cKDTree(plots) if tree is None else tree
    rmax = float(np.trace(R, axis1=1, axis2=2).max())
    ti, pj = ball_pairs(tree, z_pred, np.sqrt(threshold * (np.trace(S, axis1=1, axis2=2) + rmax)))  # none: none kept
    nu = torch.from_numpy(plots[pj] - z_pred[ti])
    Si, logdet = inv3(torch.from_numpy(S[ti] + R[pj]))
    maha = quadratic(Si, nu)
    keep = (maha <= threshold).numpy()
    ll = gaussian_loglik(maha, logdet, 3).numpy()
    return ti[keep], pj[keep], ll[keep]


def ball_pairs(tree: cKDTree, points: np.ndarray, radius) -> tuple[np.ndarray, np.ndarray]:
    """The pairs ``(i, j)`` of a point ``points[i]`` and a point ``j`` of ``tree`` within ``radius`` (one per point) of
    it, by the tree: ``(i [P], j [P])``, in the order of ``i``."""
    found = tree.query_ball_point(points, radius)
    counts = np.fromiter((len(f) for f in found), np.int64, len(found))
    pairs = np.fromiter((j for f in found for j in f), np.int64, int(counts.sum()))
    return np.repeat(np.arange(len(found)), counts), pairs


def _clusters(ti: np.ndarray, pj: np.ndarray):
    """The connected components of the bipartite graph of pairs: a label per pair and the number of clusters."""
    ut, tc = np.unique(ti, return_inverse=True)
    up, pc = np.unique(pj, return_inverse=True)
    n = len(ut) + len(up)
    graph = coo_matrix((np.ones(len(ti)), (tc, len(ut) + pc)), shape=(n, n))
    count, labels = connected_components(graph, directed=False)
    return labels[tc], count


def _groups(labels: np.ndarray, count: int):
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(count + 1))
    return [order[bounds[c]:bounds[c + 1]] for c in range(count)]


def assign(ti: np.ndarray, pj: np.ndarray, cost: np.ndarray):
    """Global nearest neighbour over the gated pairs ``(ti, pj)`` of cost ``cost``: per cluster of tracks and plots
    linked by pairs, the assignment with the most pairs and, among those, the least total cost
    (``linear_sum_assignment`` over the cluster's tracks and plots, a pair outside the gates costing more than every
    gated pair together). Returns the assigned pairs' indices into ``ti``."""
    if len(ti) == 0:
        return np.zeros(0, np.int64)
    labels, count = _clusters(ti, pj)
    sizes = np.bincount(labels, minlength=count)
    out = [np.flatnonzero(sizes[labels] == 1)]  # a cluster of one pair: assigned
    for members in _groups(labels, count):
        if len(members) < 2:
            continue
        tu, tl = np.unique(ti[members], return_inverse=True)
        pu, pl = np.unique(pj[members], return_inverse=True)
        c = cost[members] - cost[members].min()
        big = c.sum() + 1.0
        dense = np.full((len(tu), len(pu)), big)
        dense[tl, pl] = c
        index = np.full((len(tu), len(pu)), -1, np.int64)
        index[tl, pl] = members
        rows, cols = linear_sum_assignment(dense)
        chosen = index[rows, cols]
        out.append(chosen[chosen >= 0])
    return np.concatenate(out)


def jpda_probabilities(ti: np.ndarray, pj: np.ndarray, loglik: np.ndarray, n_tracks: int, pd: float, pg: float,
                       clutter_density: float, max_events: int = 20000):
    """JPDA's association probabilities of the gated pairs: per cluster, the joint events (each track takes one of its
    gated plots or none, each plot at most one track) weighted by the product over tracks of ``1 - pd pg`` (none) or
    ``pd N(nu; 0, S + R) / clutter_density`` (a plot). Returns ``beta [P]`` per pair and ``beta0 [n_tracks]`` (no plot;
    1 for a track with no gated plot). A cluster of more than ``max_events`` candidate events takes Fitzgerald's cheap
    JPDA, ``beta_ij = G_ij / (T_i + S_j - G_ij + 1 - pd pg)`` (``G`` the weights, ``T_i``, ``S_j`` their track and plot
    sums), the rest to no plot."""
    beta0 = np.ones(n_tracks)
    beta = np.zeros(len(ti))
    if len(ti) == 0:
        return beta, beta0
    miss = math.log1p(-pd * pg)
    logw = math.log(pd) + loglik - math.log(clutter_density)
    labels, count = _clusters(ti, pj)
    for members in _groups(labels, count):
        tu, tl = np.unique(ti[members], return_inverse=True)
        pu, pl = np.unique(pj[members], return_inverse=True)
        nt = len(tu)
        sizes = np.bincount(tl, minlength=nt) + 1
        if float(np.log(sizes).sum()) > math.log(max_events):
            G = np.exp(logw[members] - logw[members].max())
            b = math.exp(miss - logw[members].max())
            T = np.bincount(tl, G, nt)
            Sp = np.bincount(pl, G, len(pu))
            bij = G / (T[tl] + Sp[pl] - G + b)
            beta[members] = bij
            beta0[tu] = 1.0 - np.bincount(tl, bij, nt)
            continue
        opts = _groups(tl, nt)  # each track's pairs (local to the cluster)
        grid = np.indices(sizes).reshape(nt, -1).T  # [E, nt]: each track's option, 0 = none
        plot = np.full(grid.shape, -1, np.int64)
        lw = np.zeros(len(grid))
        for i, o in enumerate(opts):
            took = grid[:, i] > 0
            pair = o[np.maximum(grid[:, i] - 1, 0)]
            plot[:, i] = np.where(took, pl[pair], -1 - i)  # none: a value of its own, never shared
            lw += np.where(took, logw[members][pair], miss)
        srt = np.sort(plot, 1)
        valid = (np.diff(srt, axis=1) != 0).all(1) if nt > 1 else np.ones(len(grid), bool)
        w = np.exp(lw[valid] - lw[valid].max())
        w /= w.sum()
        g = grid[valid]
        for i, o in enumerate(opts):
            beta0[tu[i]] = w[g[:, i] == 0].sum()
            beta[members[o]] = np.bincount(g[:, i], w, len(o) + 1)[1:]
    return beta, beta0


# --- the tracker ---------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class TwoPointStart:
    """Initiation from two plots: a plot nobody took pairs with a seed (a plot left over ``dt`` earlier) within
    ``max_speed dt + sigma sqrt(tr R + tr R_seed)`` (m/s, and measurement standard deviations). ``vz_std``: the
    prior standard deviation (m/s) of an aircraft's vertical speed, fused with the pair's differenced velocity
    (``TrackFilter.start``; a network filter starts by its own steps and takes none); None: the pair alone. Aircraft
    climb and descend at a few m/s where a far pair's difference is uncertain by tens (chosen on the training
    scenes: docs/multi-target.md, "Initiation"). ``p_cv``: a new track's probability of flying straight, its
    constant-velocity models' share of its first mode probabilities (the rest spread evenly over the other models;
    ``IMMFilter.start``; a network filter starts by its own steps and takes none); None: the filter's own (uniform)."""

    max_speed: float = 350.0
    sigma: float = 3.0
    vz_std: float | None = 5.0
    p_cv: float | None = 0.9

    def __post_init__(self):
        for label, v in (("max_speed", self.max_speed), ("sigma", self.sigma)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"TwoPointStart.{label} must be finite and > 0, got {v}")
        check_vz_std(self.vz_std)
        if self.p_cv is not None and not 0.0 < self.p_cv < 1.0:
            raise ValueError(f"TwoPointStart.p_cv is a probability in (0, 1), got {self.p_cv}")


@dataclass(frozen=True)
class TrackScore:
    """Confirmation by a sequential track score (Blackman's log-likelihood ratio of target to clutter, tested by
    Wald's SPRT) in place of M-of-N: a tentative track's score adds, per scan, ``log(pd N(nu; 0, S + R) /
    beta_fa)`` where it takes a plot (``nu`` the innovation, ``S + R`` its covariance with the plot's, the gate's
    log-likelihood) and ``log(1 - pd pg)`` where it takes none (``pd`` the detection probability, ``pg`` the gate
    probability); the track is confirmed once its score reaches ``log((1 - beta) / alpha)`` and dropped once it
    falls to ``log(beta / (1 - alpha))`` or is still tentative ``max_scans`` scans after its seed's (the seed's the
    first). ``alpha``: the probability of confirming a false track; ``beta``: of dropping a true one
    (``alpha + beta < 1``).

    ``beta_fa``, the clutter plots per m^3, is estimated from the data: per scan, the plots no confirmed track took,
    averaged over scans exponentially (each scan's count weighing ``smoothing``; the first scan's count alone), over
    the volume of the tracker's ``Cover`` (without one, the half ball out to the farthest plot seen so far; before any
    plot, the tracker's ``clutter_density``). The score
    starts, at a two-point start, with the pair's own evidence where ``start``: ``log(pd / (beta_fa V))``, the
    second plot lying uniformly in the start's ball of volume ``V`` (radius ``max_speed dt + sigma sqrt(tr R +
    tr R_seed)``, m) under a target and being clutter with density ``beta_fa`` otherwise, plus ``log(1 - pd pg)``
    per scan missed between the two plots; 0 otherwise (the pair neutral). ``seed_scans``: the latest scan after a
    seed's whose plot can pair with the seed (1: the next scan only; ``(4, 5)``'s is 2).

    The defaults were chosen on the training scenes (5 per set at 5 s scans with 10 and with 50 clutter plots per
    scan, 1 s, 10-12 s and a noisier radar): the best geometric mean of GOSPA, none worse than ``(4, 5)`` by more
    than 0.3 %. ``alpha`` and ``beta`` are no calibrated error rates there: the scenes' clutter is uniform in range
    and elevation up to 30 degrees, not in the cover's volume, and the start's and the gate's likelihoods are
    approximations. At 5 s scans and 10 clutter plots per scan a target's hit is worth about 10-12, its start about
    6 and a miss -2.3, so ``alpha = 1e-7`` (confirming at 15.4) confirms on the third plot unless a plot is poor,
    and ``beta = 0.5`` (dropping at -0.69) drops a weak start (about 3) after two misses."""

    alpha: float = 1e-7
    beta: float = 0.5
    max_scans: int = 8
    smoothing: float = 0.1
    start: bool = True
    seed_scans: int = 2

    def __post_init__(self):
        for label, v in (("alpha", self.alpha), ("beta", self.beta)):
            if not 0.0 < v < 1.0:
                raise ValueError(f"TrackScore.{label} is a probability in (0, 1), got {v}")
        if not self.alpha + self.beta < 1.0:
            raise ValueError(f"TrackScore needs alpha + beta < 1, got {self.alpha} + {self.beta}")
        for label, v, least in (("max_scans", self.max_scans, 2), ("seed_scans", self.seed_scans, 1)):
            if int(v) != v or v < least:
                raise ValueError(f"TrackScore.{label} must be a whole number of scans >= {least}, got {v!r}")
        if not 0.0 < self.smoothing <= 1.0:
            raise ValueError(f"TrackScore.smoothing is a weight in (0, 1], got {self.smoothing}")

    @property
    def confirm_at(self) -> float:
        """The score that confirms a tentative track, ``log((1 - beta) / alpha)``."""
        return math.log((1.0 - self.beta) / self.alpha)

    @property
    def drop_at(self) -> float:
        """The score that drops a tentative track, ``log(beta / (1 - alpha))``."""
        return math.log(self.beta / (1.0 - self.alpha))


@dataclass(frozen=True)
class Cover:
    """The radar's cover, centred at the origin of the plots' frame: slant range up to ``max_range`` (m), elevation
    from ``min_elevation`` (degrees) up. A track that gets no plot at a scan and whose estimate lies outside it is
    deleted at that scan: the radar can no longer see it."""

    max_range: float
    min_elevation: float = 0.0

    def __post_init__(self):
        if not (math.isfinite(self.max_range) and self.max_range > 0) or not -90 <= self.min_elevation < 90:
            raise ValueError(f"a cover needs 0 < max_range < inf and min_elevation in [-90, 90), got "
                             f"{self.max_range}, {self.min_elevation}")

    def contains(self, pos: np.ndarray) -> np.ndarray:
        """Where positions ``[..., 3]`` (ENU, m) lie in the cover."""
        return covered(pos, self.max_range, self.min_elevation)

    @property
    def volume(self) -> float:
        """The cover's volume (m^3): the ball of radius ``max_range`` above the elevation ``min_elevation``,
        ``2 pi / 3 max_range^3 (1 - sin(min_elevation))``."""
        return 2.0 * math.pi / 3.0 * self.max_range**3 * (1.0 - math.sin(math.radians(self.min_elevation)))


def kept(x: np.ndarray, P: np.ndarray, updated: np.ndarray, misses: np.ndarray, delete_after: int,
         max_pos_std: float, cover: Cover | None, coasted: np.ndarray, min_coast: float) -> np.ndarray:
    """``[K]``: the tracks the deletion rules keep (module doc, step 6), from their estimates ``x [K, 9]``, ``P [K, 9,
    9]``, whether a plot updated them this scan, their consecutive misses and the seconds since their last plot
    ``coasted [K]``: fewer than ``delete_after`` misses or less than ``min_coast`` s, a position standard deviation
    ``sqrt(tr P_pos)`` within ``max_pos_std`` (NaN: not) and, told the radar's ``cover``, a plot this scan or an
    estimate inside it."""
    pos_std = np.sqrt(np.maximum(np.trace(P[:, 0::3, 0::3], axis1=1, axis2=2), 0.0))
    keep = ((misses < delete_after) | (coasted < min_coast)) & (pos_std <= max_pos_std)
    if cover is not None:
        keep &= updated | cover.contains(x[:, [0, 3, 6]])
    return keep


@dataclass(frozen=True)
class TrackReport:
    """One track at a scan: ``track_id`` (stable: a track keeps it from its start to its deletion, and no other
    track ever takes it), ``state [9]`` (``x, vx, ax, y, vy, ay, z, vz, az``, ENU m), ``cov [9, 9]``, ``confirmed``,
    ``updated`` (a plot was assigned to it this scan; under JPDA: a plot was in its gate)."""

    track_id: int
    state: np.ndarray
    cov: np.ndarray | None
    confirmed: bool
    updated: bool


ASSOCIATORS = ("gnn", "jpda")
DEFAULT_FILTER = MULTI_TARGET_FILTER
"""The per-track filter a ``MultiTargetTracker`` builds unless told another (``immnet.filters.registry``)."""
DELETE_AFTER = 3
"""The consecutive misses that delete a confirmed track, unless told otherwise (chosen on the training scenes)."""
MIN_COAST = 4.0
"""The seconds since its last plot before a confirmed track's misses can delete it, unless told otherwise (chosen on
the training scenes at 1 s scans; at 4.5 s and longer, ``DELETE_AFTER`` misses span more)."""
MAX_POS_STD = 5000.0
"""The position standard deviation (m) beyond which any track is deleted, unless told otherwise."""
SEEDS = ("seed_z", "seed_R", "seed_t", "seed_scan")
"""A tracker's arrays of the seeds, one row per seed (the plots left over for two-point initiation)."""


class MultiTargetTracker:
    """Tracks from unlabelled plots (module doc). ``filter``: a ``TrackFilter`` with no tracks, or a method's or a
    shipped network's name (``TrackFilter.by_name``; a network refuses ``associator="jpda"``); ``gate``: the gate
    probability ``pg`` (the chi-square threshold with 3 degrees of freedom); ``init``: ``TwoPointStart``;
    ``confirm``: ``(M, N)``, ``2 <= M <= N``, or a ``TrackScore`` (a sequential track score with the clutter
    density estimated from the plots); ``delete_after``: the consecutive misses that delete a confirmed
    track, once they span ``min_coast`` seconds since its last plot; ``max_pos_std``: the position standard
    deviation (m) beyond which any track is deleted; ``associator``: ``"gnn"`` or ``"jpda"`` (with ``pd`` the
    detection probability and ``clutter_density`` the false plots per m^3); ``r``: the measurement std (m) of plots
    given without ``R`` (None: the filter's); ``cover``: the radar's ``Cover`` (None: none), beyond which a track
    without a plot is deleted. ``min_coast``: seconds (see ``delete_after``)."""

    def __init__(self, filter: TrackFilter | str = DEFAULT_FILTER, gate: float = 0.9999,
                 init: TwoPointStart = TwoPointStart(), confirm: tuple[int, int] | TrackScore = TrackScore(),
                 delete_after: int = DELETE_AFTER,
                 max_pos_std: float = MAX_POS_STD, associator: str = "gnn", r: float | None = None, pd: float = 0.9,
                 clutter_density: float = 1e-12, jpda_max_events: int = 20000, cover: Cover | None = None,
                 min_coast: float = MIN_COAST):
        if isinstance(filter, str):
            filter = TrackFilter.by_name(filter)
        if not isinstance(filter, TrackFilter):
            raise TypeError(f"filter must be a TrackFilter or a method's name, got {type(filter).__name__}")
        if len(filter):
            raise ValueError(f"filter must hold no tracks yet, it holds {len(filter)}")
        if not 0.0 < gate < 1.0:
            raise ValueError(f"gate is a probability in (0, 1), got {gate}")
        score = confirm if isinstance(confirm, TrackScore) else None
        if score is None:
            try:
                M, N = (int(v) for v in confirm)
            except (TypeError, ValueError):
                raise ValueError(f"confirm must be (M, N) or a TrackScore, got {confirm!r}") from None
            if not 2 <= M <= N:
                raise ValueError(f"confirm (M, N) needs 2 <= M <= N (a track starts from two plots), got {confirm!r}")
        else:
            M, N = None, int(score.max_scans)
        if int(delete_after) != delete_after or delete_after < 1:
            raise ValueError(f"delete_after must be a whole number of scans >= 1, got {delete_after!r}")
        if not (math.isfinite(min_coast) and min_coast >= 0):
            raise ValueError(f"min_coast must be a finite number of seconds >= 0, got {min_coast!r}")
        if associator not in ASSOCIATORS:
            raise ValueError(f"associator must be one of {', '.join(ASSOCIATORS)}, got {associator!r}")
        if associator == "jpda" and filter.no_mixture:
            raise ValueError(filter.no_mixture)
        if not isinstance(init, TwoPointStart):
            raise TypeError(f"init must be a TwoPointStart, got {type(init).__name__}")
        for label, v in (("max_pos_std", max_pos_std), ("clutter_density", clutter_density)):
            if not v > 0:
                raise ValueError(f"{label} must be > 0, got {v}")
        if not 0.0 < pd <= 1.0:
            raise ValueError(f"pd is a probability in (0, 1], got {pd}")
        if r is not None and not (math.isfinite(r) and r > 0):
            raise ValueError(f"r must be finite and > 0, got {r}")
        self.filter, self.pg, self.threshold = filter, float(gate), float(chi2.ppf(gate, 3))
        self.init, self.M, self.N, self.delete_after = init, M, N, int(delete_after)
        self.min_coast = float(min_coast)
        self.max_pos_std, self.associator, self.pd = float(max_pos_std), associator, float(pd)
        self.clutter_density, self.jpda_max_events = float(clutter_density), int(jpda_max_events)
        if cover is not None and not isinstance(cover, Cover):
            raise TypeError(f"cover must be a Cover or None, got {type(cover).__name__}")
        self.cover = cover
        self.r = filter.r if r is None else float(r)
        self.score_rule = score
        # the latest scan after a seed whose pair can still reach M hits within N scans (a score: its seed_scans)
        self.seed_life = N - M + 1 if score is None else int(score.seed_scans)
        self.clutter_per_scan = None  # a score's estimate of the clutter plots per scan (None: no scan yet)
        self._reach = 0.0  # without a cover: the farthest plot's slant range so far (m)
        self._t, self._scan, self._next_id = None, -1, 1
        self.ids = np.zeros(0, np.int64)
        self.confirmed = np.zeros(0, bool)
        self.hits = np.zeros(0, np.int64)
        self.score = np.zeros(0)  # a TrackScore's log-likelihood ratio per track (tentative tracks')
        self.scans = np.zeros(0, np.int64)  # scans since the seed's, inclusive (tentative tracks' window)
        self.misses = np.zeros(0, np.int64)  # consecutive
        self.updated = np.zeros(0, bool)
        self.last_plot = np.zeros(0)  # the time of each track's last plot (s)
        self.seed_z, self.seed_R = np.zeros((0, 3)), np.zeros((0, 3, 3))
        self.seed_t, self.seed_scan = np.zeros(0), np.zeros(0, np.int64)
        self._x, self._P = np.zeros((0, 9)), np.zeros((0, 9, 9))

    def __len__(self) -> int:
        return len(self.ids)

    def __repr__(self) -> str:
        confirm = f"{self.M} of {self.N}" if self.score_rule is None else repr(self.score_rule)
        return (f"MultiTargetTracker({self.filter!r}, {self.associator.upper()}, confirm {confirm}; "
                f"{int(self.confirmed.sum())} confirmed of {len(self)} tracks)")

    def settings(self) -> dict:
        """What the tracker was built with, for a run's record (``immnet evaluate``'s JSON and W&B config): gate,
        confirmation, deletion, initiation and association (its filter and a scene's cover are recorded apart)."""
        confirm = [self.M, self.N] if self.score_rule is None else asdict(self.score_rule)
        return {"gate": self.pg, "confirm": confirm, "delete_after": self.delete_after,
                "min_coast": self.min_coast, "max_pos_std": self.max_pos_std, "init": asdict(self.init),
                "associator": self.associator, "pd": self.pd, "clutter_density": self.clutter_density}

    # -- input --------------------------------------------------------------------------------------------------------
    def _inputs(self, t, plots, R):
        t = float(t)
        if not math.isfinite(t):
            raise ValueError(f"step: t must be finite, got {t}")
        if self._t is not None and not t > self._t:
            raise ValueError(f"step: scan times must increase, got t = {t} after {self._t}")
        if self._t is not None:
            self.filter.check_interval(t - self._t)
        plots = np.asarray(plots, dtype=np.float64)
        if plots.size == 0:
            plots = plots.reshape(0, 3)
        if plots.ndim != 2 or plots.shape[1] != 3:
            raise ValueError(f"step: plots must be an array [N, 3] of ENU positions (m), got shape {plots.shape}")
        if not np.isfinite(plots).all():
            raise ValueError(f"step: plot {int(np.flatnonzero(~np.isfinite(plots).all(1))[0])} has a non-finite "
                             f"coordinate")
        N = len(plots)
        if R is None:
            if self.r is None:
                raise ValueError(f"step: plots without R need the tracker's r (m): {self.filter.name} assumes none")
            R = np.broadcast_to(self.r**2 * np.eye(3), (N, 3, 3)).copy()
        else:
            R = np.asarray(R, dtype=np.float64)
            if R.shape != (N, 3, 3):
                raise ValueError(f"step: R must be [N, 3, 3] for the {N} plots, got shape {R.shape}")
            bad = ~np.isfinite(R).all((1, 2)) | (np.abs(R - R.transpose(0, 2, 1)).max((1, 2), initial=0.0)
                                                   > 1e-9 * np.abs(R).max((1, 2), initial=0.0))
            if N and not bad.any():
                bad = np.linalg.eigvalsh(R)[:, 0] <= 0
            if bad.any():
                raise ValueError(f"step: R[{int(np.flatnonzero(bad)[0])}] is not a finite symmetric positive-definite "
                                 f"covariance")
        return t, plots, R

    # -- one scan -----------------------------------------------------------------------------------------------------
    def step(self, t: float, plots: np.ndarray, R: np.ndarray | None = None) -> list[TrackReport]:
        """One scan at time ``t`` (s) of plots ``[N, 3]`` (ENU, m) with covariances ``R [N, 3, 3]`` (None: ``r^2 I``).
        Returns the confirmed tracks' reports (``tracks()``: every live track)."""
        t, plots, R = self._inputs(t, plots, R)
        N, K = len(plots), len(self)
        self._scan += 1
        tree = cKDTree(plots) if N else None
        free = np.ones(N, bool)  # plots no track took
        if K:
            z_pred, S = self.filter.predict(t - self._t)
            ti, pj, ll = gate_pairs(z_pred, S, plots, R if self.filter.plot_noise else np.zeros_like(R),
                                    self.threshold, tree)
            conf = self.confirmed[ti]
            z_k = np.full((K, 3), np.nan)
            R_k = np.broadcast_to(np.eye(3), (K, 3, 3)).copy()
            if self.associator == "gnn":
                chosen = assign(ti[conf], pj[conf], -ll[conf])
                ct, cp = ti[conf][chosen], pj[conf][chosen]
                free[cp] = False
            else:
                beta, beta0 = jpda_probabilities(ti[conf], pj[conf], ll[conf], K, self.pd, self.pg,
                                                 self.clutter_density, self.jpda_max_events)
                free[pj[conf]] = False
                ct, cp = np.zeros(0, np.int64), np.zeros(0, np.int64)
            self._estimate_clutter(int(free.sum()), plots)
            tent = ~conf & free[pj]
            chosen = assign(ti[tent], pj[tent], -ll[tent])
            tt, tp = ti[tent][chosen], pj[tent][chosen]
            if self.score_rule is not None:
                gain = np.full(K, math.log1p(-self.pd * self.pg))
                gain[tt] = math.log(self.pd) + ll[tent][chosen] - math.log(self.clutter_density_now())
                self.score = np.where(self.confirmed, self.score, self.score + gain)
            free[tp] = False
            updated = np.zeros(K, bool)
            for a, b in ((ct, cp), (tt, tp)):
                z_k[a], R_k[a] = plots[b], R[b]
                updated[a] = True
            if self.associator == "gnn":
                self.filter.update(z_k, R_k)
            else:
                self._update_jpda(ti[conf], pj[conf], beta, beta0, tt, tp, plots, R, updated)
            self.updated = updated
            self.last_plot = np.where(updated, t, self.last_plot)
            self.hits = self.hits + updated
            self.misses = np.where(updated, 0, self.misses + 1)
            self.scans = self.scans + 1
        else:
            self._estimate_clutter(N, plots)
        self._initiate(t, plots[free], R[free], tree if free.all() else None)
        self._t = t
        self._x, self._P = self.filter.state()
        self._confirm_and_delete()
        return [r for r in self.tracks() if r.confirmed]

    def _estimate_clutter(self, n: int, plots: np.ndarray) -> None:
        """A score's estimate of the clutter plots per scan, with ``n`` plots no confirmed track took this scan: the
        exponential average (``TrackScore.smoothing``; the first scan's count alone); without a cover, the reach
        grown to this scan's ``plots``."""
        if self.score_rule is None:
            return
        w = self.score_rule.smoothing
        if self.cover is None and len(plots):
            self._reach = max(self._reach, float(np.linalg.norm(plots, axis=1).max()))
        self.clutter_per_scan = float(n) if self.clutter_per_scan is None else (
            (1.0 - w) * self.clutter_per_scan + w * n)

    def clutter_density_now(self) -> float:
        """The clutter density (plots per m^3) a score takes now: the estimated clutter plots per scan (at least
        1e-3) over the cover's volume, without a cover over the half ball out to the farthest plot seen so far (the
        radar's reach, as its plots show it); before any plot, ``clutter_density``."""
        if self.clutter_per_scan is None or (self.cover is None and not self._reach > 0):
            return self.clutter_density
        volume = self.cover.volume if self.cover is not None else 2.0 * math.pi / 3.0 * self._reach**3
        return max(self.clutter_per_scan, 1e-3) / volume

    def _start_score(self, dt: np.ndarray, radius: np.ndarray, scans: np.ndarray) -> np.ndarray:
        """New tracks' first scores (``TrackScore.start``): the pair's evidence, from the seeds' ages ``dt`` (s),
        the start's ball radii (m) and the scans from the seed's to this one, inclusive."""
        if self.score_rule is None or not self.score_rule.start:
            return np.zeros(len(dt))
        log_vol = math.log(4.0 * math.pi / 3.0) + 3.0 * np.log(radius)
        return (math.log(self.pd) - math.log(self.clutter_density_now()) - log_vol
                + (scans - 2) * math.log1p(-self.pd * self.pg))

    def _update_jpda(self, ti, pj, beta, beta0, tt, tp, plots, R, updated):
        """The mixture update of every track: confirmed tracks' gated plots with their JPDA probabilities, tentative
        tracks' assigned plot with probability 1 (none: no plot with probability 1)."""
        b0 = beta0.copy()
        b0[tt] = 0.0
        rows, cols = np.concatenate([ti, tt]), np.concatenate([pj, tp])
        updated[ti] = True
        self.filter.update_mixture(rows, plots[cols], R[cols], np.concatenate([beta, np.ones(len(tt))]), b0)

    def _initiate(self, t, plots, R, tree):
        """Pair this scan's free plots with the seeds, start a tentative track per pair, keep the rest as seeds."""
        self._keep(SEEDS, self._scan - self.seed_scan <= self.seed_life)
        n = len(plots)
        paired = np.zeros(n, bool)
        if n and len(self.seed_z):
            tree = cKDTree(plots) if tree is None else tree
            dt = t - self.seed_t
            tr_seed = np.trace(self.seed_R, axis1=1, axis2=2)
            tr_plot = np.trace(R, axis1=1, axis2=2)
            sig = self.init.sigma
            si, pq = ball_pairs(tree, self.seed_z, self.init.max_speed * dt + sig * np.sqrt(tr_seed + tr_plot.max()))
            dist = np.linalg.norm(plots[pq] - self.seed_z[si], axis=1)
            radius = self.init.max_speed * dt[si] + sig * np.sqrt(tr_seed[si] + tr_plot[pq])  # each pair's ball
            ok = dist <= radius
            si, pq, dist, radius = si[ok], pq[ok], dist[ok], radius[ok]
            chosen = assign(si, pq, dist / (self.init.max_speed * dt[si]))
            si, pq, radius = si[chosen], pq[chosen], radius[chosen]
            if len(si):
                self.filter.start(plots[pq], R[pq], self.seed_z[si], self.seed_R[si], dt[si], self.init.vz_std,
                                  self.init.p_cv)
                k = len(si)
                scans = self._scan - self.seed_scan[si] + 1
                self._append(ids=np.arange(self._next_id, self._next_id + k), confirmed=np.zeros(k, bool),
                             hits=np.full(k, 2), score=self._start_score(dt[si], radius, scans), scans=scans,
                             misses=np.zeros(k, np.int64), updated=np.ones(k, bool), last_plot=np.full(k, t))
                self._next_id += k
                paired[pq] = True
                self._keep(SEEDS, np.delete(np.arange(len(self.seed_z)), si))
        rest = ~paired
        n_rest = int(rest.sum())
        self._append(seed_z=plots[rest], seed_R=R[rest], seed_t=np.full(n_rest, t),
                     seed_scan=np.full(n_rest, self._scan))

    def _keep(self, names, keep) -> None:
        """The rows ``keep`` (a mask or indices) of each of the arrays ``names``."""
        for name in names:
            setattr(self, name, getattr(self, name)[keep])

    def _append(self, **rows) -> None:
        """Each array named by a keyword with its rows appended."""
        for name, value in rows.items():
            setattr(self, name, np.concatenate([getattr(self, name), value]))

    def _confirm_and_delete(self):
        if self.score_rule is None:
            self.confirmed = self.confirmed | (self.hits >= self.M) & (self.scans <= self.N)
            hopeless = ~self.confirmed & (self.hits + (self.N - self.scans) < self.M)
        else:
            rule = self.score_rule
            self.confirmed = self.confirmed | (self.score >= rule.confirm_at)
            hopeless = ~self.confirmed & ((self.score <= rule.drop_at) | (self.scans >= self.N))
        misses = np.where(self.confirmed, self.misses, 0)  # a tentative track is not deleted for its misses
        keep = ~hopeless & kept(self._x, self._P, self.updated, misses, self.delete_after, self.max_pos_std,
                                self.cover, self._t - self.last_plot, self.min_coast)
        if keep.all():
            return
        self.filter.drop(keep)
        self._keep(("ids", "confirmed", "hits", "score", "scans", "misses", "updated", "last_plot", "_x", "_P"), keep)

    def data_mode_probs(self) -> np.ndarray | None:
        """Every live track's data-mode probabilities ``[K, 4]`` (CV, CA, CT+, CT-) as of the last scan, in the order
        of ``tracks()``; None where the filter has none (``IMMFilter.data_mode_probs``)."""
        get = getattr(self.filter, "data_mode_probs", None)
        return None if get is None else get()

    def tracks(self) -> list[TrackReport]:
        """Every live track (confirmed and tentative) as of the last scan."""
        return [TrackReport(int(i), self._x[k].copy(), self._P[k].copy(), bool(self.confirmed[k]),
                            bool(self.updated[k])) for k, i in enumerate(self.ids)]
