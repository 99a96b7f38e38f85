"""The output correction: a learned, causal correction of the fused estimate from the track's whole history.

After the IMM's fusion (and the track start's join) a GRU reads, scan by scan, what the filter knows after that
scan and adds a correction to the position it reports::

    o_t = x_t + r [delta_t, 0, 0 per axis],    delta_t = W h_t,    h_t = GRU(h_{t-1}, f_t)

with ``f_t`` (nothing absolute: nothing of where the track is, only what the filter says of it)

    (z_t - p_t) / r (0 where missed), a detection flag, v_t / 100, a_t, sqrt(diag P_t) of the position / r,
    of the velocity and of the acceleration, the mode probabilities (every group's), r / 5, log(interval)

``x_t = [p, v, a]`` the fused estimate, ``P_t`` its covariance, ``r`` the measurement std the filter experts use,
``sqrt(("memory", "r2"))`` (each track's as told, a fixed one, or the gain's running estimate from the track's own
measurements: ``FilterGain(r=...)``). The correction is an output: the filters, the fused state and
everything the next scan's stages read are unchanged, so it cannot destabilize the IMM; ``IMMNet`` reports
``("output", "state")`` in place of the fused estimate (``IMMNet.estimate``). Its recurrent state
``("memory", "output_hidden")`` starts at zero with each track and moves from the scan the track has an estimate
(its start's first detection) on. The reported covariance stays the filter's (docs/immnet.md "The output
correction").

``whiten=True`` reads and writes the innovation in the frame of the measurement noise the filter experts use,
``R`` (``("memory", "r2")``: each detection's covariance where they are told it, ``FilterGain(r="detection")``, else
``r^2 I``), ``L`` its Cholesky factor (``R = L L^T``)::

    o_t = x_t + [L delta_t, 0, 0 per axis]

with ``L^-1 (z_t - p_t)`` in place of ``(z_t - p_t) / r``, ``sqrt(diag(L^-1 P_pos L^-T))`` in place of the position's
``sqrt(diag P) / r``, and ``log(sqrt(diag R) / 5 m)`` (three features) in place of ``r / 5``: a radar's plot, 40 m in range
and hundreds of metres across it at 100 km, is read as the three independent unit errors it is, whatever its geometry.

``CorrectionEnsemble`` runs several such corrections on one filter and reports the mean of their corrections (each
trained as a run of its own, joined by ``immnet.training.export.join_corrections``).

An OutputCorrection's weights are laid out as ``scripts/learned_residual.py``'s network (``inp``, ``gru``, ``out``),
which runs the same GRU over whole sequences (``torch.nn.GRU``) on the outputs of a model-based filter's own fast
path: the two are held equal in ``tests/test_output_correction.py``.
"""

from __future__ import annotations

import torch
from torch import nn

from immnet import keys
from immnet.imm.kalman import as_covariance
from immnet.imm.option import flag
from immnet.motion import ACC_VIEW, POS_VIEW, VEL_VIEW, Modes
from immnet.stages.base import Stage, measured, scan_interval

VEL_SCALE, ACC_SCALE, R_SCALE = 100.0, 1.0, 5.0


def cholesky_noise(R: torch.Tensor) -> torch.Tensor:
    """``L [B, 3, 3]`` lower triangular with ``R = L L^T`` of covariances ``R [B, 3, 3]``; where one is not positive
    definite to the dtype's precision, the square root of its (clamped) diagonal."""
    L, info = torch.linalg.cholesky_ex(R)
    diag = torch.diag_embed(R.diagonal(dim1=-2, dim2=-1).clamp_min(1e-12).sqrt())
    return torch.where((info == 0)[..., None, None], L, diag)


def noise_covariance(noise: torch.Tensor) -> torch.Tensor:
    """The measurement noise ``("memory", "r2")`` as a covariance ``[B, 3, 3]``: a variance ``[B]`` as ``r^2 I``, a
    covariance (filter experts told each detection's, ``[B, 3, 3]``) as it is."""
    return as_covariance(noise if noise.dim() >= 3 else noise.reshape(-1, 1, 1), noise)


def noise_std(noise: torch.Tensor) -> torch.Tensor:
    """One std per track ``[B, 1]`` of the measurement noise ``("memory", "r2")``: ``r`` of a variance, the root mean
    of a covariance's diagonal (``sqrt(tr R / 3)``)."""
    if noise.dim() >= 3:
        noise = noise.diagonal(dim1=-2, dim2=-1).mean(-1)
    return noise.clamp_min(1e-12).sqrt().reshape(-1, 1)


def std_of(var: torch.Tensor) -> torch.Tensor:
    """``sqrt(max(var, 0))``, with a zero gradient where that is 0: ``sqrt``'s derivative at 0 is infinite, and a
    feature no scan uses (a track before its first detection, whose covariance is zero) gets a zero gradient, which
    ``0 * inf`` would turn into NaN in every weight."""
    live = var > 0
    return torch.where(live, torch.where(live, var, torch.ones_like(var)).sqrt(), torch.zeros_like(var))


def _features(z, x, P, mu, dt, scaled, pos_std, noise) -> torch.Tensor:
    """``f_t`` (module doc) with the innovation ``scaled(z_t - p_t)`` (0 where missed), the position's standard
    deviations ``pos_std [B, 3]`` and the noise's features ``noise [B, 1 or 3]`` as the caller scales them; a
    non-finite entry is 0."""
    seen = measured(z)
    d = scaled(torch.where(seen, z - x[..., POS_VIEW], torch.zeros_like(z)))
    std = std_of(P.diagonal(dim1=-2, dim2=-1))
    log_dt = torch.log(torch.as_tensor(dt, dtype=x.dtype, device=x.device)).expand(x.shape[0], 1)
    f = torch.cat([
        d, seen.to(x.dtype), x[..., VEL_VIEW] / VEL_SCALE, x[..., ACC_VIEW] / ACC_SCALE,
        pos_std, std[..., VEL_VIEW], std[..., ACC_VIEW], mu.reshape(mu.shape[0], -1).to(x.dtype), noise, log_dt,
    ], -1)
    return torch.where(torch.isfinite(f), f, torch.zeros_like(f))


def whitened_features(z, x, P, mu, L, dt) -> torch.Tensor:
    """``f_t`` with ``whiten`` (module doc) ``[B, 23 + G M]``: as :func:`correction_features`, in the frame of the
    measurement noise's Cholesky factor ``L [B, 3, 3]``; a non-finite entry is 0."""
    pos = P[..., POS_VIEW, POS_VIEW]
    Li_P = torch.linalg.solve_triangular(L, pos, upper=False)
    white_pos = torch.linalg.solve_triangular(L, Li_P.transpose(-1, -2), upper=False)  # L^-1 P L^-T
    R_std = (L * L).sum(-1).clamp_min(1e-12).sqrt()  # sqrt(diag(L L^T))
    white_d = lambda d: torch.linalg.solve_triangular(L, d.unsqueeze(-1), upper=False).squeeze(-1)  # noqa: E731
    return _features(z, x, P, mu, dt, white_d, std_of(white_pos.diagonal(dim1=-2, dim2=-1)), torch.log(R_std / R_SCALE))


def correction_features(z, x, P, mu, r, dt) -> torch.Tensor:
    """``f_t`` of the module doc ``[B, 21 + G M]``: measurements ``z [B, 3]`` (NaN: missed), fused estimate
    ``x [B, 9]``, its covariance ``P [B, 9, 9]``, mode probabilities ``mu [B, M]`` or ``[B, G, M]``, ``r [B, 1]``,
    ``dt`` a float or ``[B, 1]``; a non-finite entry is 0."""
    pos_std = std_of(P.diagonal(dim1=-2, dim2=-1)[..., POS_VIEW]) / r
    return _features(z, x, P, mu, dt, lambda d: d / r, pos_std, r / R_SCALE)


class OutputCorrection(Stage):
    """The output correction (module doc): ``hidden`` units in ``layers`` GRU layers. Built by
    ``IMMNet(correction=...)`` after the step's fusion, for its model set and ``modes`` (the number of mode
    probabilities it reads). ``whiten``: the innovation in the measurement noise's frame (module doc); off, the
    scalar ``r`` (the root mean of the diagonal where the filter experts are told each detection's covariance)."""

    in_keys = [keys.MEASUREMENT, keys.FUSED, keys.FUSED_COV, keys.EXPERT_PROBS, keys.OUTPUT_HIDDEN, keys.OUTPUT_SEEN,
               keys.AGE, keys.NOISE_VAR]
    out_keys = [keys.OUTPUT, keys.OUTPUT_HIDDEN, keys.OUTPUT_SEEN]

    shared = ("modes",)

    def __init__(self, model_set=None, dt: float = 1.0, hidden: int = 128, layers: int = 2, modes: str = "joint",
                 whiten: bool = False):
        super().__init__(model_set)
        if int(hidden) < 1 or int(layers) < 1:
            raise ValueError(f"hidden and layers must be at least 1, got hidden={hidden!r}, layers={layers!r}")
        self.whiten = flag(whiten, "whiten")
        self.dt = float(dt)
        self.hidden, self.layers = int(hidden), int(layers)
        self.n_groups = Modes.parse(modes).n_groups or 1
        self.n_features = (23 if whiten else 21) + self.n_groups * self.n_experts
        self.inp = nn.Linear(self.n_features, self.hidden)
        self.gru = nn.GRU(self.hidden, self.hidden, num_layers=self.layers, batch_first=True)
        self.out = nn.Linear(self.hidden, 3)
        self.knock_out()  # untrained, it corrects nothing: the step is its filter's

    def wire(self, upstream: set) -> None:
        """It reads the fused covariance and the filters' measurement variance: the stages before it must write them
        (filter experts, whose gain keeps ``("memory", "r2")``)."""
        if keys.FUSED_COV not in upstream or keys.NOISE_VAR not in upstream:
            raise ValueError("the output correction reads the fused covariance ('fused', 'cov') and the filters' "
                             "measurement variance ('memory', 'r2'): its step needs filter experts "
                             "(immnet.stages.filtering)")

    def carry_spec(self, batch: int, experts_alone: bool = False, dtype=torch.float32, device=None) -> dict:
        """The GRU's state, zero before a track starts, and whether it has seen the track's first detection."""
        return {keys.OUTPUT_HIDDEN: torch.zeros(batch, self.layers, self.hidden, dtype=dtype, device=device),
                keys.OUTPUT_SEEN: torch.zeros(batch, dtype=torch.long, device=device)}

    def knock_out(self) -> None:
        """No correction: the step reports its filter's estimate (``IMMNet.knock_out("correction")``)."""
        with torch.no_grad():
            self.out.weight.zero_()
            self.out.bias.zero_()

    def inputs(self, td) -> tuple[torch.Tensor, torch.Tensor]:
        """What this scan's correction reads: the features ``f_t`` (module doc) and the noise's scale that turns a
        correction into metres, the Cholesky factor ``L [B, 3, 3]`` (``whiten``) or the std ``r [B, 1]``."""
        z, x = td.get(keys.MEASUREMENT), td.get(keys.FUSED)
        noise = td.get(keys.NOISE_VAR).to(x.dtype)
        dt, _ = scan_interval(td, self.dt)
        if self.whiten:
            L = cholesky_noise(noise_covariance(noise))
            return whitened_features(z, x, td.get(keys.FUSED_COV), td.get(keys.EXPERT_PROBS), L, dt), L
        r = noise_std(noise)
        return correction_features(z, x, td.get(keys.FUSED_COV), td.get(keys.EXPERT_PROBS), r, dt), r

    def shift(self, td, h: torch.Tensor, inputs=None) -> tuple[torch.Tensor, torch.Tensor]:
        """This scan's correction of the reported position ``[B, 3]`` (m; zero where the track has no estimate yet
        or is at its first detection) and the GRU's next state, from its state ``h [B, layers, hidden]``; ``inputs``:
        this scan's ``inputs(td)`` where the caller has them."""
        f, scale = self.inputs(td) if inputs is None else inputs
        w = self.inp.weight
        y, states, g = torch.relu(self.inp(f.to(w.dtype))), [], self.gru
        for layer in range(self.layers):  # one scan: the GRU's cells, layer by layer (nn.GRU's numbers)
            y = torch.gru_cell(y, h[:, layer].to(w.dtype), getattr(g, f"weight_ih_l{layer}"),
                               getattr(g, f"weight_hh_l{layer}"), getattr(g, f"bias_ih_l{layer}"),
                               getattr(g, f"bias_hh_l{layer}"))
            states.append(y)
        h_new = torch.stack(states, 1)
        delta = self.out(y).to(f.dtype)
        step = (scale @ delta.unsqueeze(-1)).squeeze(-1) if self.whiten else scale * delta
        running = _has_estimate(td).reshape(-1, 1)
        # a track's first detection is reported as its filter reports it (the measurement, as every tracker's); the
        # correction starts at the scan after, when its state has seen the track
        corrects = running & (td.get(keys.OUTPUT_SEEN) >= 1).reshape(-1, 1)
        return (torch.where(corrects, step, torch.zeros_like(delta)),
                torch.where(running[..., None], h_new.to(h.dtype), h))

    def forward(self, td):
        shift, h = self.shift(td, td.get(keys.OUTPUT_HIDDEN))
        _report(td, shift, h)
        return td


def _has_estimate(td) -> torch.Tensor:
    """``[B]`` bool: the track has an estimate, from its first detection on."""
    return td.get(keys.AGE) >= 1


def _report(td, shift: torch.Tensor, h: torch.Tensor) -> None:
    """Write the step's output (the fused estimate, its position shifted by ``shift``), the correction's state ``h``
    and whether it has seen the track (from the scan the track has an estimate on)."""
    x, seen = td.get(keys.FUSED), td.get(keys.OUTPUT_SEEN)
    out = x.clone()
    out[..., POS_VIEW] = x[..., POS_VIEW] + shift
    td.set(keys.OUTPUT, out)
    td.set(keys.OUTPUT_HIDDEN, h)
    running = _has_estimate(td).reshape(seen.shape)
    td.set(keys.OUTPUT_SEEN, torch.where(running, torch.ones_like(seen), seen))


class CorrectionEnsemble(Stage):
    """``members`` output corrections on one filter, their corrections averaged: each reads what the filter knows
    (``OutputCorrection``) and keeps its own GRU state (``("memory", "output_hidden")`` ``[B, K, layers, hidden]``),
    and the step reports ``x_t + mean_k r [delta_t^k, 0, 0]``. The filters run once, whatever ``members``. Each
    member is trained as a run of its own on the same filter (the same network, one correction), and
    ``immnet.training.export.join_corrections`` joins their checkpoints (docs/immnet.md "The output correction")."""

    in_keys = OutputCorrection.in_keys
    out_keys = OutputCorrection.out_keys

    shared = ("modes",)

    def __init__(self, model_set=None, dt: float = 1.0, members: int = 2, hidden: int = 128, layers: int = 2,
                 modes: str = "joint", whiten: bool = False):
        super().__init__(model_set)
        if int(members) < 2:
            raise ValueError(f"an ensemble has at least 2 members, got members={members!r} (one: OutputCorrection)")
        self.members = nn.ModuleList(OutputCorrection(model_set, dt, hidden, layers, modes, whiten)
                                     for _ in range(int(members)))
        self.hidden, self.layers = self.members[0].hidden, self.members[0].layers

    def wire(self, upstream: set) -> None:
        self.members[0].wire(upstream)

    def carry_spec(self, batch: int, experts_alone: bool = False, dtype=torch.float32, device=None) -> dict:
        one = self.members[0].carry_spec(batch, experts_alone, dtype, device)
        return {keys.OUTPUT_HIDDEN: torch.stack([one[keys.OUTPUT_HIDDEN]] * len(self.members), 1),
                keys.OUTPUT_SEEN: one[keys.OUTPUT_SEEN]}

    def knock_out(self) -> None:
        """No correction from any member (``IMMNet.knock_out("correction")``)."""
        for member in self.members:
            member.knock_out()

    def forward(self, td):
        h = td.get(keys.OUTPUT_HIDDEN)
        inputs = self.members[0].inputs(td)  # every member reads the same features
        shifts, states = zip(*(member.shift(td, h[:, k], inputs) for k, member in enumerate(self.members)))
        _report(td, torch.stack(shifts).mean(0), torch.stack(states, 1))
        return td
