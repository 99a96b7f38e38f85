"""The clairvoyant Kalman filter: the bound no causal tracker beats on average (docs/spec.md section 3).

It knows each trajectory's true mode sequence ``mode[t]``, turn rates ``turn_rate[t]`` and
measurement noise ``r``, and runs one Kalman filter with the truth's time-varying transition:

* ``F_t = F_CV``, ``F_CA`` or ``F_CT(turn_rate[t])`` by ``mode[t]`` (the step ``t-1 -> t``);
* the truth's process noise ``Q = sigma_q^2 G G^T``, ``G`` per axis ``[dt^2/2, dt, 0]``;  ``R = r^2 I``;

each of the interval ``dt`` before scan ``t`` (``immnet.data.times.scan_intervals``: any interval, per track
and scan; where all are one value the matrices are built once from it).

Every generator statistic it uses comes from the data's ``DataSpec`` (``immnet.data.spec``): ``sigma_q``,
the CA draw's variance and (``SwitchClairvoyantKF``) the turn-rate prior. A bound only stays a bound when
told the statistics of the data it scores, so ``configure(meta)`` takes them from a data set's
``meta.json`` (``immnet evaluate`` calls it; ``--sigma-q`` overrides ``sigma_q``); without meta they are
3D-LAST's (``DataSpec()``: sigma_q 0.2). See docs/evaluation.md.

At the first step of a CA segment (``mode[t] = CA != mode[t-1]``, ``t >= 1``) the generator writes a
newly drawn acceleration into the state before ``F_CA``. The bound knows a switch happened, not
the draw: before predicting it resets the acceleration mean to 0, removes its correlations, and
sets its variance to that of the draw (``DataSpec.ca_acc_var``): horizontal magnitude
``a ~ U[lo, hi]`` m/s^2 at a uniform direction gives ``E[a_x^2] = E[a^2] / 2 = (hi^3 - lo^3) / (3 (hi - lo)) / 2``
per horizontal axis (3D-LAST's ``U[0.5, 3]``: 1.7917); vertical ``U[-v, v]`` gives ``v^2 / 3`` (0.03).

It starts like every other method: from the first detection, at its scan (``initial_state`` with the true r,
``first_detection``), except that where the track is in a CA segment there it gives the acceleration the draw's
variance above; no estimate (NaN) before a track's first detection.

``SwitchClairvoyantKF`` is told less: the true mode sequence (so when a switch happens) and r, not
the turn rates. It runs an extended Kalman filter of ``[x, w]``: at every turn onset, and wherever
the turn rate changes within a turn (a soft-bound turn), ``w`` restarts from the prior of a turn,
``|w| ~ U[turn_rate_min_deg, turn_rate_max_deg]`` in the mode's sign (``DataSpec.turn_rate_prior_deg``; 3D-LAST's
``U[1, 10]`` deg/s: mean 5.5, standard deviation 2.6), and is estimated from the measurements. It is a
tighter reference than the bound for what a tracker that detected every switch at once could reach.

Both are configurations of the core's scan loop (``immnet.imm.runner.run``) with the truth's modes as its oracle:
the bound over CV, CA and CT at the true rate, ``SwitchClairvoyantKF`` over extended Kalman filters of CV, CA, CT+
and CT- with the interaction's onset priors and a ``restart`` where a turn's rate changes within it. Each is also a
configuration of IMMNet's step with nothing learned and an oracle (``network()``: the truth's modes in the classifier's
slot, ``immnet.stages.TrueModeUpdate``), held equal to ``track`` (docs/core.md).
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

from immnet import keys
from immnet.data.spec import DataSpec
from immnet.filters.base import Method, as_dtype, interval_or_intervals, output
from immnet.filters.imm import ACC_STD, first_detection, initial_state
from immnet.imm.interaction import enter, onset_priors
from immnet.imm.kalman import predict
from immnet.imm.runner import run
from immnet.motion import CA, CT_POS, N_MODES, ca_matrix, ct_jacobian, ct_matrix, ct_propagate, cv_matrix, process_noise


class ClairvoyantKF(Method):
    """Kalman filter with the true modes, turn rates and r of each trajectory; a bound, not a tracker."""

    needs = (keys.MODE, keys.TURN_RATE, keys.R)
    ground_truth = True
    any_interval = True

    def __init__(self, sigma_q: float | None = None, acc_var=None, spec=None, dtype="float64", name: str = "clairvoyant"):
        """``spec``: the data's ``DataSpec`` (or a dict of its fields; default 3D-LAST's), where every statistic
        not given comes from; ``sigma_q`` and ``acc_var`` fix those two whatever the spec says."""
        if sigma_q is not None and not sigma_q >= 0:
            raise ValueError(f"sigma_q must be >= 0, got {sigma_q}")
        self.fixed_sigma_q = None if sigma_q is None else float(sigma_q)
        self.fixed_acc_var = None if acc_var is None else tuple(float(v) for v in acc_var)
        self.dtype, self.name = as_dtype(dtype), name
        self.set_spec(spec)

    def set_spec(self, spec) -> None:
        """Take the statistics not fixed at construction from ``spec`` (a ``DataSpec``, a dict of its fields, None: 3D-LAST)."""
        spec = spec if isinstance(spec, DataSpec) else DataSpec.from_dict(spec)
        self.spec = spec
        self.sigma_q = spec.sigma_q if self.fixed_sigma_q is None else self.fixed_sigma_q
        self.acc_var = spec.ca_acc_var() if self.fixed_acc_var is None else self.fixed_acc_var

    def configure(self, meta: dict | None, sigma_q: float | None = None) -> str | None:
        """Take the generator statistics of the data set described by ``meta`` (``load_dataset``'s): its
        ``spec`` where it has one; ``sigma_q`` (``immnet evaluate --sigma-q``) overrides. Returns a note
        when the data carries no spec and 3D-LAST's statistics stand (an ``.npz``), else None."""
        if sigma_q is not None:
            if not sigma_q >= 0:
                raise ValueError(f"--sigma-q must be >= 0, got {sigma_q}")
            self.fixed_sigma_q = float(sigma_q)
        spec = (meta or {}).get("spec")
        self.set_spec(spec)
        if spec is None and sigma_q is None and self.fixed_sigma_q is None:
            return (f"{self.name}: the data carries no generator spec (no meta.json); using 3D-LAST's statistics "
                    f"(sigma_q {self.sigma_q:g}); give --sigma-q for data generated with another")
        return None

    def check(self, batch: TensorDict) -> None:
        """As every method's, and a ValueError where a scan has no mode label (``mode`` -1: real flights,
        padding): the bound needs the true mode at every scan."""
        super().check(batch)
        if bool((torch.as_tensor(batch[keys.MODE]) < 0).any()):
            raise ValueError(f"{self.name} needs the true mode at every scan (ground truth); this data has scans "
                             f"without a label (mode -1: real flights, or padding)")

    def _inputs(self, batch: TensorDict):
        """``z [B, T, 3]``, ``mode [B, T]``, ``turn_rate [B, T]``, ``r [B]`` in this method's dtype, and the
        interval of scan ``t`` as a function ``interval(t)``: a float where every scan's is one value, else
        the tracks' ``[B]`` (``scan_intervals``)."""
        self.check(batch)
        z = batch[keys.MEASUREMENTS].to(self.dtype)
        dev = z.device
        r = torch.as_tensor(batch[keys.R], dtype=self.dtype, device=dev).reshape(z.shape[0])
        dt = interval_or_intervals(batch, self.dtype, dev)
        interval = (lambda t: dt) if isinstance(dt, float) else (lambda t: dt[:, t])
        return z, batch[keys.MODE].to(dev), batch[keys.TURN_RATE].to(self.dtype), r, interval

    def network(self, dt: float = 1.0):
        """This bound as IMMNet's step with nothing learned and an oracle (docs/core.md, "Every tracker as a
        configuration"): filter experts of CV, CA and a turn (each the truth's white acceleration noise
        ``Q(sigma_q, dt)``, ``FilterGain(model_noise=sigma_q)``; the turn told the truth's rate of each scan,
        ``turn_rate="data"``), told each track's ``r`` (``r="data"``), the IMM's mix with the onset priors of the
        data's spec (a CA segment's new acceleration), the truth's modes in the classifier's slot
        (``TrueModeUpdate``: the mix takes each expert's prior from the true mode's expert and the fusion is that
        expert's), and a start from the first detection with the spec's start covariance, the acceleration the CA
        draw's for the CA expert (``start_acc_std``; only the true mode's expert at the start carries on). An
        ``IMMNet`` in this method's dtype, ``eval``; give ``rollout`` the truth's ``mode`` and ``turn_rate`` over
        the sequence as ``truth=ClairvoyantKF.truth(batch)`` and each track's ``r``. It filters what ``track``
        filters, to float64 rounding (``tests/test_filters_clairvoyant.py``). A ValueError where this bound's CA draw's
        variance is fixed apart from its spec (the step's onset prior is the spec's)."""
        return self._oracle_network([{"class_path": "immnet.motion.AdaptiveTurn"}], dt, turn_rate="data")

    def _oracle_network(self, turns: list, dt: float, **gain):
        """IMMNet with nothing learned and the truth's modes (``network()``): filter experts of CV, CA (white
        acceleration noise, the CA expert starting with the draw's acceleration variance) and ``turns``, told each
        track's ``r``, the IMM's mix with the spec's onset priors; ``gain``: the filter gain's other arguments."""
        from immnet.stages.network import IMMNet

        if tuple(self.acc_var) != tuple(self.spec.ca_acc_var()):
            raise ValueError(f"{self.name}: acc_var {self.acc_var} is not its spec's CA draw ({self.spec.ca_acc_var()}); "
                             "the step's onset prior is the spec's")
        models = [{"class_path": "immnet.motion.ConstantVelocity", "init_args": {"noise": "white"}},
                  {"class_path": "immnet.motion.ConstantAcceleration", "init_args": {"noise": "white"}}, *turns]
        gain = {"class_path": "immnet.stages.filtering.FilterGain", "init_args": {
            "model_noise": self.sigma_q, "r": "data", "interaction": "imm", "onset": True, "spec": self.spec.to_dict(),
            "start_acc_std": [ACC_STD, None] + [ACC_STD] * len(turns), **gain}}
        oracle = {"class_path": "immnet.stages.TrueModeUpdate"}
        net = IMMNet(model_set=models, gain=gain, classifier=oracle, dt=dt, p_stay=0.5, start_detections=1)
        return net.to(self.dtype).eval()

    @staticmethod
    def truth(batch: TensorDict) -> dict:
        """The oracle's inputs over a batch's scans, for ``network().rollout(..., truth=)``: the data's mode and turn
        rate ``[B, T]``."""
        return {keys.TRUE_MODE: batch[keys.MODE], keys.TRUE_TURN_RATE: batch[keys.TURN_RATE]}

    def track(self, batch: TensorDict) -> TensorDict:
        """One Kalman filter with the truth's transition at each scan: the core's scan loop
        (``immnet.imm.runner.run``) over the filters CV, CA and CT at the true rate, whose mode
        probabilities are the truth's (``oracle``), so that each scan predicts with the true mode's model
        from the previous true mode's posterior, with the CA draw's prior where a CA segment starts (the
        interaction's onset prior)."""
        z, mode, w, r, interval = self._inputs(batch)
        dtype, dev = z.dtype, z.device
        B, T, _ = z.shape
        x, P = initial_state(z, r)
        start = first_detection(z)
        at_start = mode.gather(1, start.to(mode.device)[:, None])[:, 0]
        # the CA segment's draw (the generator writes the first into x_0)
        P[at_start == CA, 2::3, 2::3] = torch.diag(torch.tensor(self.acc_var, dtype=dtype, device=dev))
        onset = onset_priors([False, True, False], [False] * 3, [0.0] * 3, n=9, acc_var=self.acc_var)

        def matrices(d):
            """``F_CV``, ``F_CA`` ``[B, 9, 9]`` and ``Q`` (``[9, 9]``; ``[B, 1, 9, 9]`` for ``d [B]``: the 3 filters')."""
            Q = process_noise(self.sigma_q, d, "white", dtype=dtype, device=dev)
            return (cv_matrix(d, dtype, dev).expand(B, 9, 9), ca_matrix(d, dtype, dev).expand(B, 9, 9),
                    Q if Q.dim() == 2 else Q[:, None])

        fixed = matrices(interval(0)) if isinstance(interval(0), float) else None  # one interval: built once

        def transition(t, x0, P0):
            d = interval(t)
            Fcv, Fca, Q = fixed if fixed is not None else matrices(d)
            return predict(x0, P0, torch.stack([Fcv, Fca, ct_matrix(w[:, t], d, dtype, dev)], 1), Q)

        one = torch.full((3, 3), 1.0 / 3.0, dtype=dtype, device=dev)
        states, _, _ = run(z, x[:, None].expand(B, 3, 9), P[:, None].expand(B, 3, 9, 9), one[0].expand(B, 3), one,
                           transition, r**2, onset=onset, oracle=mode.clamp(max=CT_POS), start=start)
        return output(states, measurements=z)


class SwitchClairvoyantKF(ClairvoyantKF):
    """Knows the true modes (the switches) and r, estimates each turn's rate: a tighter reference."""

    def __init__(self, sigma_q: float | None = None, acc_var=None, turn_prior_deg=None, spec=None, dtype="float64",
                 name: str = "clairvoyant-switch"):
        """As :class:`ClairvoyantKF`; ``turn_prior_deg`` ``(mean, std)`` fixes the turn-rate prior too."""
        if turn_prior_deg is not None:
            mean, std = (float(v) for v in turn_prior_deg)
            if not (mean > 0 and std >= 0):
                raise ValueError(f"turn_prior_deg needs a mean > 0 and a std >= 0, got {turn_prior_deg}")
        self.fixed_turn_prior = None if turn_prior_deg is None else (mean, std)
        super().__init__(sigma_q, acc_var, spec, dtype, name)

    def set_spec(self, spec) -> None:
        super().set_spec(spec)
        self.turn_prior_deg = self.spec.turn_rate_prior_deg() if self.fixed_turn_prior is None else self.fixed_turn_prior

    def network(self, dt: float = 1.0):
        """This reference as IMMNet's step with nothing learned and an oracle: ``ClairvoyantKF.network``'s, over
        CV, CA and turns CT+ and CT- that estimate their rate unbounded (``FilterGain(turn_rate="free")``, each
        entering a turn with the spec's rate prior in its sign: the models' nominal rate and ``rate_std0_deg``), the
        experts re-entered with their onset priors where a turn's rate changes within it (``restart="data"``, the
        truth's ``("truth", "restart")``). Give ``rollout`` ``truth=SwitchClairvoyantKF.truth(batch)``. A ValueError
        where the CA draw's variance or the turn prior is fixed apart from the spec."""
        if tuple(self.turn_prior_deg) != tuple(self.spec.turn_rate_prior_deg()):
            raise ValueError(f"{self.name}: turn_prior_deg {self.turn_prior_deg} is not its spec's "
                             f"({self.spec.turn_rate_prior_deg()}); the step's onset prior is the spec's")
        mean, std = self.turn_prior_deg
        bounds = {"min_deg": min(1.0, mean), "max_deg": max(10.0, mean)}
        turns = [{"class_path": "immnet.motion.AdaptiveTurn", "init_args": {"turn_rate_deg": sign * mean, **bounds}}
                 for sign in (1.0, -1.0)]
        return self._oracle_network(turns, dt, rate_std0_deg=std, turn_rate="free", restart="data")

    @staticmethod
    def restarts(mode: torch.Tensor, rate: torch.Tensor) -> torch.Tensor:
        """Where a turn's rate changes within the turn ``[B, T]`` (bool): the truth draws a rate anew without a mode
        switch (a soft-bound turn), from its ``mode`` and ``turn_rate`` ``[B, T]``."""
        restart = torch.zeros_like(mode, dtype=torch.bool)
        restart[:, 1:] = (mode[:, 1:] >= CT_POS) & (mode[:, 1:] == mode[:, :-1]) & (rate[:, 1:] != rate[:, :-1])
        return restart

    @staticmethod
    def truth(batch: TensorDict) -> dict:
        """The oracle's inputs over a batch's scans: the data's mode and where a turn's rate changes within it."""
        return {keys.TRUE_MODE: batch[keys.MODE],
                keys.TRUE_RESTART: SwitchClairvoyantKF.restarts(batch[keys.MODE], batch[keys.TURN_RATE])}

    def track(self, batch: TensorDict) -> TensorDict:
        """The core's scan loop (``immnet.imm.runner.run``) over extended Kalman filters of ``[x, w]`` for CV, CA,
        CT+ and CT- whose modes are the truth's (``oracle``): each scan predicts with the true mode's filter from
        the previous true mode's posterior, entering it with its onset prior where the mode switched (a CA
        segment's new acceleration, a turn's rate from the prior in its sign); where the rate changes within a
        turn, the turn filter enters from itself with that prior (``restart``)."""
        z, mode, rate, r, interval = self._inputs(batch)
        dtype, dev = z.dtype, z.device
        B = z.shape[0]
        H = torch.eye(10, dtype=dtype, device=dev)[0:9:3]  # the positions of [x, w]

        def matrices(d):
            """``F_CV``, ``F_CA`` and ``Q`` of ``[x, w]`` over an interval ``d`` (``[10, 10]``; ``[B, 10, 10]`` for ``d [B]``),
            ``w`` dropped (a turn filter's own rate enters with its onset prior)."""
            blocks = (cv_matrix(d, dtype, dev), ca_matrix(d, dtype, dev),
                      process_noise(self.sigma_q, d, "white", dtype=dtype, device=dev))
            Fcv, Fca, Q = (torch.nn.functional.pad(A, (0, 1, 0, 1)) for A in blocks)  # w's row and column zero
            return Fcv.expand(B, 10, 10), Fca.expand(B, 10, 10), Q if Q.dim() == 2 else Q[:, None]

        fixed = matrices(interval(0)) if isinstance(interval(0), float) else None  # one interval: built once

        def transition(t, x0, P0):
            """The filters' predictions ``[B, 4, 10]``: CV and CA linear, each turn at its own rate (its Jacobian)."""
            d = interval(t)
            Fcv, Fca, Q = fixed if fixed is not None else matrices(d)
            dd = d if isinstance(d, float) else d[:, None]
            turns, w = x0[:, 2:, :9], x0[:, 2:, 9]
            J = torch.cat([torch.stack([Fcv, Fca], 1), ct_jacobian(turns, w, dd)], 1)
            xp, Pp = predict(x0, P0, J, Q)
            return torch.cat([xp[:, :2], torch.cat([ct_propagate(turns, w, dd), w[..., None]], -1)], 1), Pp

        # what a filter becomes where the truth switches into it (a new acceleration into CA, a rate into a turn,
        # in the mode's sign), and where a turn's rate changes within it: the onset priors of CV, CA, CT+, CT-
        onset = onset_priors([False, True, False, False], [False, False, True, True], [0.0, 0.0, 1.0, -1.0], n=10,
                             acc_var=self.acc_var, rate_prior_deg=self.turn_prior_deg)
        x9, P9 = initial_state(z, r)
        x, P = torch.nn.functional.pad(x9, (0, 1)), torch.nn.functional.pad(P9, (0, 1, 0, 1))  # w 0, its variance 0
        x, P = enter(x[:, None], P[:, None], *onset)  # each filter as the track starts in its mode
        one = torch.full((N_MODES, N_MODES), 1.0 / N_MODES, dtype=dtype, device=dev)
        states, _, _ = run(z, x, P, one[0].expand(B, N_MODES), one, transition, r**2, onset=onset, oracle=mode, H=H,
                           restart=self.restarts(mode, rate), start=first_detection(z))
        return output(states[..., :9], measurements=z)
