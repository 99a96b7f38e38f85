"""State-dependent mode transitions at the edge of the surveillance region and of the flight envelope
(a "range guard", which also knows the speed bounds).

An IMM's Markov chain says a switch is as likely anywhere. Some switches are not: an aircraft that
reaches the edge of the airspace it must stay in turns back, whatever it was doing. Estimators with
state-dependent transition probabilities (Seah & Hwang, "State-dependent transition hybrid
estimation", IEEE TAC 2009) let the *estimated state* drive the transition matrix through such
guard conditions. The 3D-LAST generator has exactly such rules, the soft range bounds of docs/spec.md
section 2: a target outside ``outer`` (33 km) moving outward, or inside ``inner`` (4 km) moving
inward, turns at ``rate_deg`` (8 deg/s) toward (away from) the radar until its heading points back
by 30 degrees (radial speed beyond ``clear_share`` of its speed), then flies CV.

``RangeGuard.events`` evaluates these rules on each mode-matched filter's previous posterior (as the
generator does on ``x_{t-1}``), softened by logistic ramps of a few standard errors so that an
estimate near a threshold gives a probability, not a jump:

* onset, from any mode: ``P(rho > outer) P(v_r > 0)`` (or the inner rule), into the turn mode of the
  turn's sign (``sign(l x v)`` at the outer bound, the opposite at the inner);
* range clear, from a turn mode: the first scan at which ``v_r / |v| < -clear_share`` (outer, within
  ``clear_margin`` of the bound) or ``> clear_share`` (inner): the condition on the posterior and not on
  the same velocity turned back one scan at the filter's rate; weighted by how close that rate is to
  the bound's rate (a scheduled turn flying past the threshold is not told to stop);

``guarded_transition`` turns them into a transition matrix per track and source mode,
``Pi_eff[b, i, :] = (1 - g) Pi[i, :] + g (event target)``, and reports the share of each entry that a
bound turn made, so that the interaction can give a turn entered at the bound its known rate.

* speed onset, from a CA filter only: the chance that the estimate has just left the speed bounds
  (``|v| < speed_min or |v| > speed_max or |vz| > vz_max`` now but not a scan ago, the estimate's own
  acceleration taking it back: ``(F_now - F_before) / (1 - F_before)``), into either turn mode with
  even odds (the generator draws the bound turn's sign at random);
* speed clear: such a turn lasts one scan, then the target flies CV. A filter's posterior does not
  say how its mode was entered, so the caller carries it: ``fresh [B, M]``, the share of each turn
  filter's mixed prior that entered at a speed bound on the last scan (``guarded_transition``
  returns each entry's speed share; ``fresh_j = sum_i mu_{i|j} speed_ij``), clears to CV.

``speeds=False`` leaves the speed rules out (the range rules alone).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch

from immnet.imm.option import Option, positive
from immnet.motion import DEG

G_MAX = 0.999  # the most probable a guard event is made


@dataclass(frozen=True)
class RangeGuard(Option):
    """Soft range and speed bounds as guard conditions (module doc); the bounds default to the 3D-LAST generator's
    (``immnet.data.spec.DataSpec.guard_bounds`` gives another data set's), the ramps' widths and tolerances are the
    guard's own."""

    ARG = "guard"

    outer: float = 33_000.0  # m: beyond, moving outward -> turn toward the radar
    inner: float = 4_000.0  # m: within, moving inward -> turn away from it
    rate_deg: float = 8.0  # the bound turn's rate
    clear_share: float = 0.5  # the turn clears once the radial speed is beyond this share of the speed (heading back 30 deg)
    clear_margin: float = 3_000.0  # m: a clear is looked for within this distance of the bound
    range_soft: float = 10.0  # m: logistic width of the range thresholds
    speed_soft: float = 1.0  # m/s: of the radial-speed sign
    share_soft: float = 0.02  # of the radial share at a clear
    rate_tol_deg: float = 2.0  # how close a turn's rate must be to rate_deg to be the bound's turn
    rate_std_deg: float = 0.2  # the rate prior of a turn entered at the bound
    speeds: bool = True  # the speed rules too: a CA leaving the speed bounds turns for one scan
    speed_min: float = 40.0  # m/s: horizontal speed bounds of a CA segment
    speed_max: float = 330.0
    vz_max: float = 25.0  # m/s: vertical speed bound of a CA segment
    bound_speed_soft: float = 1.0  # m/s: logistic width of the speed bounds (a CA filter's speed error)

    def __post_init__(self):
        for name in (f.name for f in fields(self) if f.name != "speeds"):  # every field but speeds is a number
            positive(getattr(self, name), f"RangeGuard.{name} must be a positive number")
        if not isinstance(self.speeds, bool):
            raise ValueError(f"RangeGuard.speeds must be true or false, got {self.speeds!r}")
        if self.inner >= self.outer:
            raise ValueError(f"RangeGuard.inner ({self.inner}) must be below outer ({self.outer})")
        if self.speed_min >= self.speed_max:
            raise ValueError(f"RangeGuard.speed_min ({self.speed_min}) must be below speed_max ({self.speed_max})")
        if self.clear_share >= 1:
            raise ValueError(f"RangeGuard.clear_share must be below 1, got {self.clear_share}")

    def events(self, x: torch.Tensor, w: torch.Tensor, dt: float):
        """Guard event probabilities per track and mode-matched filter, from posteriors ``x [..., 9]``
        and turn rates ``w [...]`` (rad/s): ``(onset_pos, onset_neg, clear, speed)``, each ``[...]``.

        ``onset_pos`` / ``onset_neg``: a range-bound turn starts with ``w > 0`` / ``w < 0``; ``clear``: a
        range-bound turn flown at ``w`` ends (meaningful for turn filters only); ``speed``: the estimate has
        just left the speed bounds (a CA there turns for one scan; 0 with ``speeds=False``).
        """
        lx, vx, ly, vy = x[..., 0], x[..., 1], x[..., 3], x[..., 4]
        rho = torch.sqrt(lx * lx + ly * ly).clamp_min(1.0)
        hs = torch.sqrt(vx * vx + vy * vy).clamp_min(1e-3)
        vr = (lx * vx + ly * vy) / rho
        ccw = torch.sigmoid((lx * vy - ly * vx) / (rho * self.speed_soft))  # P(l x v > 0)
        outer = torch.sigmoid((rho - self.outer) / self.range_soft) * torch.sigmoid(vr / self.speed_soft)
        inner = torch.sigmoid((self.inner - rho) / self.range_soft) * torch.sigmoid(-vr / self.speed_soft)
        onset_pos = outer * ccw + inner * (1 - ccw)
        onset_neg = outer * (1 - ccw) + inner * ccw
        # the velocity one scan earlier at this filter's rate: rotated back by w dt
        c, s = torch.cos(w * dt), torch.sin(w * dt)
        vx0, vy0 = c * vx + s * vy, -s * vx + c * vy
        share, share0 = vr / hs, (lx * vx0 + ly * vy0) / (rho * hs)
        k = self.clear_share
        out_clear = torch.sigmoid((-k - share) / self.share_soft) * torch.sigmoid((share0 + k) / self.share_soft)
        in_clear = torch.sigmoid((share - k) / self.share_soft) * torch.sigmoid((k - share0) / self.share_soft)
        near_out = torch.sigmoid((rho - (self.outer - self.clear_margin)) / self.range_soft)
        near_in = torch.sigmoid(((self.inner + self.clear_margin) - rho) / self.range_soft)
        at_rate = torch.exp(-0.5 * ((w.abs() - self.rate_deg * DEG) / (self.rate_tol_deg * DEG)) ** 2)
        clear = (out_clear * near_out + in_clear * near_in).clamp(max=1.0) * at_rate
        if self.speeds:
            # the first scan out of bounds, not every one: the chance of being out now but not a scan ago,
            # the speeds a scan ago from the estimate's own acceleration (a CA filter's)
            ax, ay, vz, az = x[..., 2], x[..., 5], x[..., 7], x[..., 8]
            hs0 = torch.sqrt((vx - ax * dt) ** 2 + (vy - ay * dt) ** 2)
            now, before = self._speed_out(hs, vz), self._speed_out(hs0, vz - az * dt)
            speed = ((now - before) / (1 - before).clamp_min(1e-6)).clamp(0.0, 1.0)
        else:
            speed = torch.zeros_like(clear)
        return onset_pos, onset_neg, clear, speed

    def _speed_out(self, hs: torch.Tensor, vz: torch.Tensor) -> torch.Tensor:
        """P(outside the speed bounds), softened by ``bound_speed_soft``."""
        s = self.bound_speed_soft
        inside = (torch.sigmoid((hs - self.speed_min) / s) * torch.sigmoid((self.speed_max - hs) / s)
                  * torch.sigmoid((self.vz_max - vz.abs()) / s))
        return 1 - inside


def guarded_transition(
    Pi: torch.Tensor,
    events: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor],
    modes: torch.Tensor,
    fresh: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The transition matrix per track ``[B, M, M]`` (rows: from, columns: to), the bound-turn share of
    each entry and its speed-bound part, each ``[B, M, M]``.

    ``Pi [M, M]``: the Markov matrix; ``events``: ``RangeGuard.events`` of each source filter, each
    ``[B, M]``; ``modes [M]``: each filter's data mode (0 CV, 1 CA, 2 CT+, 3 CT-); ``fresh [B, M]``: the
    share of each filter's last mixed prior that entered at a speed bound (the one-scan turn clears to
    CV; ``None``: none). An event's target mode is shared evenly among the filters of that mode; a speed
    onset leaves CA filters only, a clear turn filters only, and a model set without the target mode
    ignores the event.
    """
    onset_pos, onset_neg, clear, speed = events
    dtype = onset_pos.dtype

    def target(mode: int) -> torch.Tensor:
        hit = (modes == mode).to(dtype)
        return hit / hit.sum().clamp_min(1.0)

    to_pos, to_neg, to_cv = target(2), target(3), target(0)
    is_turn = (modes >= 2).to(dtype)
    is_ca = (modes == 1).to(dtype)
    onset_pos = onset_pos * to_pos.sum()
    onset_neg = onset_neg * to_neg.sum()
    speed_pos = 0.5 * speed * is_ca * to_pos.sum()  # the speed-bound turn's sign is a coin flip
    speed_neg = 0.5 * speed * is_ca * to_neg.sum()
    if fresh is not None:
        clear = (clear + fresh.to(dtype)).clamp(max=1.0)
    clear = clear * is_turn * to_cv.sum()
    # the events are exclusive (the ramps may overlap a little); g stays below 1 so that every mode keeps
    # some prior mass (a certain event would leave the others' mixing weights 0 / 0)
    total = onset_pos + onset_neg + speed_pos + speed_neg + clear
    g = total.clamp(max=G_MAX)
    scale = torch.where(g > 0, g / total.clamp_min(1e-30), torch.zeros_like(g))
    onset_pos, onset_neg, speed_pos, speed_neg, clear = (e * scale for e in (onset_pos, onset_neg, speed_pos, speed_neg, clear))
    by_speed = speed_pos[..., None] * to_pos + speed_neg[..., None] * to_neg  # [B, i, j]
    bound = onset_pos[..., None] * to_pos + onset_neg[..., None] * to_neg + by_speed
    Pi_eff = (1 - g)[..., None] * Pi.to(dtype) + bound + clear[..., None] * to_cv
    denom = Pi_eff.clamp_min(1e-30)
    return Pi_eff, (bound / denom).clamp(max=1.0), (by_speed / denom).clamp(max=1.0)


def fresh_share(w: torch.Tensor, speed_share: torch.Tensor) -> torch.Tensor:
    """The share of each filter's mixed prior that entered at a speed bound, ``[B, M]``, from the mixing
    weights ``mu_{i|j}`` ``w [B, i, j]`` and ``guarded_transition``'s speed share of each entry."""
    return (w * speed_share).sum(-2)


AS_CONFIGURED = "checkpoint"
"""A setting left as the checkpoint or method configures it: a tracker's range guard (``build_method``,
``load_network``), and a network's ``adapt``, ``r`` and ``reacquire`` (``load_network``)."""


def parse_guard(text: str):
    """A ``--guard`` option: ``checkpoint`` (``AS_CONFIGURED``), ``none`` or ``OUTER,INNER`` (metres) -> the guard
    setting of ``immnet.tracking.load_network`` and ``immnet.evaluation.build_method``: ``AS_CONFIGURED``, None
    (no guard: data from another region) or ``{"outer", "inner"}`` (``RangeGuard``'s range thresholds)."""
    text = text.strip().lower()
    if text == AS_CONFIGURED:
        return AS_CONFIGURED
    if text == "none":
        return None
    try:
        outer, inner = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--guard must be 'checkpoint', 'none' or 'OUTER,INNER' in metres, got {text!r}") from None
    return {"outer": outer, "inner": inner}
