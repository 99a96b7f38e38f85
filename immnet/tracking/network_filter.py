"""A shipped network as the multi-target tracker's per-track filter (``immnet.filters.multi.TrackFilter``).

    tracker = MultiTargetTracker("radar-5s")                    # or NetworkFilter.pretrained("radar-5s")

The tracks are the rows of one streaming ``Tracker`` (``immnet.tracking.tracker``): every scan of every live track is
one call of the network's step, and each track runs as the network runs alone on its plots (``Tracker.step``: its
own frame, its own start, coasting through an interval longer than the network's range):

* ``start`` runs the new tracks' two plots through a fresh ``Tracker`` of their own (the seed's plot, then the
  plot that paired with it, ``dt`` after it; the seed's scan takes ``dt`` as its interval too; a network of one
  interval coasts through the scans between the two, missed, as it would alone) and appends their carry to the live
  tracks';
* ``predict`` gives each track's prediction as the network makes it: the estimate and covariance it reports after a
  scan without a detection (its coast; for filter experts and a Bayesian mode update, each expert's prior combined
  with the predicted mode probabilities, the IMM prior, moved by the output correction where the network has one).
  The carry is left as it was: ``update`` runs the scan again from it with the plots;
* the gate's measurement noise is the network's own: a network told each plot's covariance (``radar-5s``,
  ``radar-11s``) filters with that plot's ``R``, which the tracker adds per plot; a network that estimates each
  track's noise (``real-5s`` ...) filters with its estimate ``r^2 I``, which ``predict`` adds to the covariance it
  gives (``plot_noise`` False: the tracker adds nothing);
* ``update`` is one scan of the network with each track's plot (a NaN row: missed, the network coasts);
* ``drop`` keeps the rows asked for; the others' carry is unchanged;
* ``check_interval`` refuses, before the tracker changes anything, a scan at an interval the network does not take.

JPDA is refused: its update is a mixture of the hypotheses' posteriors, and a network's carry (its recurrent memory,
its noise estimate, its history of plots) is one track's history, which no weighted blend of carries stands for.
"""

from __future__ import annotations

import numpy as np
import torch

from immnet import keys
from immnet.checkpoints import shipped
from immnet.filters.multi import TrackFilter
from immnet.tracking.networks import check_scan, network_from, read_checkpoint
from immnet.tracking.tracker import Tracker


class NetworkFilter(TrackFilter):
    """A network's tracks for the multi-target tracker (module doc). ``tracker``: a streaming ``Tracker`` whose
    network and ``max_position`` it takes (not its tracks); ``name``: what it is, for messages (None: the tracker's). The tracker's ``max_coast`` is
    set to ``inf``: the multi-target tracker deletes a track after its misses, the network never restarts one."""

    def __init__(self, tracker: Tracker, name: str | None = None):
        if not isinstance(tracker, Tracker):
            raise TypeError(f"tracker must be an immnet.tracking.Tracker, got {type(tracker).__name__}")
        net = tracker.net
        if not net.has_cov:
            raise ValueError(f"{name or tracker}: {net.no_cov_reason()}; the multi-target tracker gates with the "
                             f"filter's covariance")
        if net.start.told_r:
            raise ValueError(f"{name or tracker} is told each track's measurement std (r='data'): the multi-target "
                             f"tracker has none per track to tell it (load it with r=<metres> or without r)")
        if net.gain.reacquire is not None:
            raise ValueError(f"{name or tracker} restarts its own tracks (re-acquisition, immnet.imm.reacquire): the "
                             f"multi-target tracker starts and deletes them (load it with reacquire=None)")
        if net.gain.start_vz_std is not None:
            raise ValueError(f"{name or tracker} starts a track with its own prior on the vertical speed "
                             f"(start_vz_std): the multi-target tracker starts them (load it with start_vz_std=None)")
        self.net = net
        self.name = name or tracker.name or (tracker.path.name if tracker.path is not None else "network")
        self.plot_noise = bool(net.start.told_cov)  # told each plot's covariance: the tracker adds it per plot
        self.no_mixture = (f"{self.name} is a network: JPDA needs a mixture update over a track's gated plots, and a "
                           f"network's carry (its recurrent memory and noise estimate) is one track's history, which "
                           f"no weighted blend stands for; use GNN (associator gnn)")  # why JPDA is refused
        self.r = None
        self._tr = self._fresh(tracker)
        self._x, self._P = np.zeros((0, 9)), np.zeros((0, 9, 9))
        self._probs = np.zeros((0, 4))

    @classmethod
    def pretrained(cls, name: str) -> "NetworkFilter":
        """The shipped network ``name`` (``immnet.checkpoints.SHIPPED``) with its own settings but re-acquisition and
        the start's prior on the vertical speed (``radar-5s``, ``radar-11s``): the multi-target tracker's initiation and
        deletion take their place. (With its prior, Huber's update weighs a pair's second plot far from a level start
        as an outlier: a pair of clutter plots 1.5 km apart in height became a track 1.3 km wide that gated clutter.)"""
        path = shipped(name)
        config, state = read_checkpoint(path)  # read once; the settings taken off where the network has them
        given = (config.get("gain") or {}).get("init_args") or {}
        net = network_from(config, state, path,
                           **{name: None for name in ("reacquire", "start_vz_std") if given.get(name) is not None})
        return cls(Tracker(net, name=name, path=path), name)

    def _fresh(self, like: Tracker) -> Tracker:
        return Tracker(self.net, like.max_position, float("inf"), like.name, like.path)

    def __len__(self) -> int:
        return 0 if self._tr.carry is None else int(self._tr.carry.batch_size[0])

    def __repr__(self) -> str:
        return f"NetworkFilter({self.name}, {len(self)} tracks)"

    # the streaming tracker's state: its carry and its per-track memory
    _FIELDS = ("carry", "fresh", "since", "last", "origin")

    def _save(self):
        return {f: getattr(self._tr, f) for f in self._FIELDS}

    def _restore(self, saved) -> None:
        for f, v in saved.items():
            setattr(self._tr, f, v)

    def _step(self, tr: Tracker, z: np.ndarray, R: np.ndarray | None, dt) -> None:
        """One scan of ``tr`` with ``z [K, 3]`` (NaN rows: missed), the plots' ``R`` where the network is told it;
        keeps the reported estimate, covariance and data-mode probabilities."""
        z = torch.from_numpy(np.ascontiguousarray(z, dtype=np.float64))
        cov = None
        if self.plot_noise:
            R = np.broadcast_to(np.eye(3), (len(z), 3, 3)) if R is None else np.asarray(R, dtype=np.float64)
            cov = torch.from_numpy(np.where(np.isnan(z.numpy()).any(-1)[:, None, None], np.eye(3), R))
        out = tr.step(z, dt=torch.as_tensor(dt, dtype=torch.float64), R=cov)
        tr.carry = tr.carry.select(*self.net.carry_keys)  # what the next scan reads
        self._out = tuple(out.get(k).double().numpy() for k in (keys.FUSED, keys.FUSED_COV, keys.MODE_PROBS))

    # -- the protocol -------------------------------------------------------------------------------------------------
    def check_interval(self, dt: float) -> None:
        """A ValueError, before anything changes, unless the network takes a scan ``dt`` seconds after the last:
        an interval it was trained at, or (a network trained over a range) one longer than the range, coasted through
        in equal intervals inside it (``Tracker.step``'s rule)."""
        iv = torch.tensor([float(dt)], dtype=torch.float64)
        check_scan(self.net, iv, torch.zeros(1, dtype=torch.bool), self.name)

    def _multiples(self, dt: np.ndarray) -> np.ndarray:
        """The scans each start's interval spans for a network of one interval (its ``dt`` times a whole number: the
        seed's scan, missed scans, the pair's scan); 1 for a network over a range (``Tracker.step`` cuts those)."""
        if getattr(self.net, "interval_range", None) is not None:
            return np.ones(len(dt), np.int64)
        k = np.rint(dt / float(self.net.dt))
        whole = (k >= 2) & np.isclose(dt, k * float(self.net.dt), rtol=1e-9, atol=0.0)
        return np.where(whole, k, 1).astype(np.int64)

    @torch.no_grad()
    def start(self, z, R, z_prev=None, R_prev=None, dt=None, vz_std=None, p_cv=None) -> None:
        z, R = np.asarray(z, dtype=np.float64).reshape(-1, 3), np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
        k = len(z)
        if k == 0:
            return
        if z_prev is None:
            raise ValueError(f"{self.name}: a network's track starts from two plots (z_prev, R_prev and dt)")
        zp, Rp = np.asarray(z_prev, np.float64).reshape(-1, 3), np.asarray(R_prev, np.float64).reshape(-1, 3, 3)
        dt = np.broadcast_to(np.asarray(dt, dtype=np.float64).reshape(-1), (k,)).copy()
        spans = self._multiples(dt)
        parts, order = [], []
        for n in np.unique(spans):  # the starts spanning n scans together: seed, n - 1 missed scans, pair
            rows = np.flatnonzero(spans == n)
            new = self._fresh(self._tr)
            new.reset(len(rows))
            each = dt[rows] / n
            self._step(new, zp[rows], Rp[rows], each)
            for _ in range(n - 1):
                self._step(new, np.full((len(rows), 3), np.nan), None, each)
            self._step(new, z[rows], R[rows], each)
            parts.append((new, self._out))
            order.append(rows)
        back = torch.from_numpy(np.argsort(np.concatenate(order), kind="stable"))  # the rows in the order given
        fields = {f: torch.cat([getattr(new, f) for new, _ in parts])[back] for f in self._FIELDS}
        x, P, probs = (np.concatenate([out[i] for _, out in parts])[back.numpy()] for i in range(3))
        if self._tr.carry is None:
            self._restore(fields)
        else:
            self._restore({f: torch.cat([getattr(self._tr, f), v]) for f, v in fields.items()})
        self._x, self._P = np.concatenate([self._x, x]), np.concatenate([self._P, P])
        self._probs = np.concatenate([self._probs, probs])

    @torch.no_grad()
    def predict(self, dt: float):
        K = len(self)
        if K == 0:
            return np.zeros((0, 3)), np.zeros((0, 3, 3))
        self._dt = float(dt)
        saved = self._save()
        self._step(self._tr, np.full((K, 3), np.nan), None, self._dt)
        noise = self._tr.carry.get(keys.NOISE_VAR, None) if not self.plot_noise else None
        self._restore(saved)
        x, P, _ = self._out
        S = P[:, 0::3, 0::3].copy()
        if not self.plot_noise:  # the network's own measurement model: its estimate r^2 per track
            S += noise.double().numpy().reshape(K, 1, 1) * np.eye(3)
        return x[:, 0::3].copy(), S

    @torch.no_grad()
    def update(self, z, R) -> None:
        if len(self) == 0:
            return
        self._step(self._tr, np.asarray(z, dtype=np.float64).reshape(-1, 3), R, self._dt)
        self._x, self._P, self._probs = self._out

    def update_mixture(self, track, z, R, beta, beta0) -> None:
        raise ValueError(self.no_mixture)

    def drop(self, keep) -> None:
        keep = np.asarray(keep, dtype=bool)
        self._x, self._P, self._probs = self._x[keep], self._P[keep], self._probs[keep]
        if not keep.all():  # the carry's rows kept (none kept: no carry)
            rows = torch.from_numpy(keep)
            self._restore({f: v[rows] if keep.any() else None for f, v in self._save().items()})

    def state(self):
        return self._x.copy(), self._P.copy()

    def data_mode_probs(self) -> np.ndarray:
        """Every track's data-mode probabilities ``[K, 4]`` (CV, CA, CT+, CT-) as the network reports them."""
        return self._probs.copy()

