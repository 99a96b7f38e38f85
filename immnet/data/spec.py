"""Every parameter of the 3D-LAST scenario (docs/spec.md section 2, spec version 1), as one dataclass.

Units SI (m, s, m/s, m/s^2), angles in degrees where the name says ``_deg``. A YAML file of
``field: value`` lines overrides any subset (``immnet data generate --config FILE``).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass
from pathlib import Path

import yaml

from immnet.data.radar import check_plot_settings, check_scan_interval

SPEC_VERSION = 1
"""Bumped whenever the generator's output for a given (seed, n, spec) changes. ``dt_jitter`` (0 by default)
draws nothing at 0, so that every spec of version 1 still gives the same bytes: it did not bump the version."""

NM = 1852.0
"""One nautical mile in metres."""


@dataclass(frozen=True)
class DataSpec:
    """The 3D-LAST scenario. Defaults are docs/spec.md section 2."""

    # time and noise
    T: int = 400
    dt: float = 1.0  # the scan interval (s): fixed, or the mean of U[dt - dt_jitter, dt + dt_jitter]
    dt_jitter: float = 0.0  # half-width (s) of each scan interval's uniform draw; 0: every interval is dt
    r_min: float = 1.0  # measurement noise std r ~ U[r_min, r_max] m, once per trajectory
    r_max: float = 7.0
    sigma_q: float = 0.2  # truth process noise (m/s^2), G per axis [dt^2/2, dt, 0]
    p_miss: float = 0.0  # probability that a scan's detection is missed (NaN), from the third scan on
    # initial state
    range_min: float = 5_000.0  # horizontal range U[range_min, range_max], uniform azimuth
    range_max: float = 30_000.0
    alt_min: float = 1_000.0
    alt_max: float = 10_000.0
    speed_min: float = 50.0  # horizontal speed, uniform heading
    speed_max: float = 300.0
    vz_max: float = 5.0  # vertical speed U[-vz_max, vz_max]
    # schedule and segment parameters
    n_segments: int = 3
    min_segment: int = 40
    turn_rate_min_deg: float = 1.0  # |w| ~ U[min, max] deg/s, sign by mode
    turn_rate_max_deg: float = 10.0
    ca_acc_h_min: float = 0.5  # CA horizontal magnitude U[min, max] at a uniform direction
    ca_acc_h_max: float = 3.0
    ca_acc_v_max: float = 0.3  # CA vertical U[-max, max]
    # soft bounds
    bound_range_outer: float = 33_000.0
    bound_range_inner: float = 4_000.0
    bound_speed_min: float = 40.0
    bound_speed_max: float = 330.0
    bound_vz: float = 25.0
    bound_turn_rate_deg: float = 8.0
    bound_clear_heading_deg: float = 30.0
    # hard bounds (a trajectory leaving them is redrawn)
    hard_range_min: float = 0.5 * NM  # 926 m
    hard_range_max: float = 20.0 * NM  # 37,040 m
    hard_speed_max: float = 340.0
    hard_alt_min: float = 100.0
    hard_alt_max: float = 15_000.0
    # a radar's plots at the origin (all three stds given, LOW > 0, drawn U[LOW, HIGH] per trajectory): noise in slant
    # range (m), azimuth and elevation (degrees), converted to east-north-up with each plot's covariance (meas_cov),
    # in place of r N(0, I3); 0: not asked for (immnet.data.radar.plots)
    sigma_range_min: float = 0.0
    sigma_range_max: float = 0.0
    sigma_azimuth_min_deg: float = 0.0
    sigma_azimuth_max_deg: float = 0.0
    sigma_elevation_min_deg: float = 0.0
    sigma_elevation_max_deg: float = 0.0
    outliers: float = 0.0  # with plots: the share of detections whose noise is outlier_scale times larger
    outlier_scale: float = 10.0

    def __post_init__(self):
        check_numbers(self)
        if self.T < 1:
            raise ValueError(f"T must be >= 1, got {self.T}")
        check_scan_interval(self.dt, self.dt_jitter)
        if not 0.0 <= self.p_miss < 1.0:
            raise ValueError(f"p_miss must be in [0, 1), got {self.p_miss}")
        if self.n_segments < 1:
            raise ValueError(f"n_segments must be >= 1, got {self.n_segments}")
        if self.n_segments * self.min_segment > self.T:
            raise ValueError(
                f"{self.n_segments} segments of at least {self.min_segment} steps do not fit in T={self.T}"
            )
        for lo, hi in (("r_min", "r_max"), ("range_min", "range_max"), ("alt_min", "alt_max"),
                       ("speed_min", "speed_max"), ("turn_rate_min_deg", "turn_rate_max_deg"),
                       ("ca_acc_h_min", "ca_acc_h_max"), ("hard_range_min", "hard_range_max"),
                       ("hard_alt_min", "hard_alt_max")):
            if getattr(self, lo) > getattr(self, hi):
                raise ValueError(f"{lo}={getattr(self, lo)} exceeds {hi}={getattr(self, hi)}")
        pairs = dict(zip(PLOT_PAIRS, self.plot_stds()))
        given = [name for name, (lo, hi) in pairs.items() if lo or hi]
        for name, (lo, hi) in pairs.items():
            if name in given and not 0 < lo <= hi:
                raise ValueError(f"{name} is a pair LOW,HIGH with 0 < LOW <= HIGH, got {lo:g},{hi:g}")
        check_plot_settings(given, self.outliers, self.outlier_scale)
        if self.outliers > 0 and not given:
            raise ValueError("outliers need a radar's plots: give sigma_range, sigma_azimuth and sigma_elevation")

    @property
    def plots(self) -> bool:
        """The measurements are a radar's plots (range, azimuth, elevation): the ``sigma_*`` pairs given."""
        return self.sigma_range_max > 0

    def plot_stds(self) -> tuple[tuple[float, float], tuple[float, float], tuple[float, float]]:
        """The ``(LOW, HIGH)`` pairs of the plots' stds: slant range (m), azimuth and elevation (degrees)."""
        return tuple((getattr(self, f"{n}_min{u}"), getattr(self, f"{n}_max{u}")) for n, u in PLOT_PAIRS.items())

    # --- what a filter told this spec's statistics needs ------------------------------------------
    def ca_acc_var(self) -> tuple[float, float, float]:
        """Variance per axis (x, y, z) of a newly drawn CA acceleration (docs/spec.md section 2): horizontal
        magnitude ``a ~ U[lo, hi]`` at a uniform direction gives ``E[a_x^2] = E[a^2] / 2`` with
        ``E[a^2] = (hi^3 - lo^3) / (3 (hi - lo))`` (3D-LAST's ``U[0.5, 3]``: 1.7917); vertical ``U[-v, v]``
        gives ``v^2 / 3`` (0.03)."""
        lo, hi, v = self.ca_acc_h_min, self.ca_acc_h_max, self.ca_acc_v_max
        mean_sq = (hi**3 - lo**3) / (3.0 * (hi - lo)) if hi > lo else lo**2
        return mean_sq / 2.0, mean_sq / 2.0, v**2 / 3.0

    def turn_rate_prior_deg(self) -> tuple[float, float]:
        """Mean and standard deviation (deg/s) of a turn rate's magnitude ``U[turn_rate_min_deg,
        turn_rate_max_deg]`` (3D-LAST's ``U[1, 10]``: 5.5 and 2.6)."""
        lo, hi = self.turn_rate_min_deg, self.turn_rate_max_deg
        return (lo + hi) / 2.0, (hi - lo) / 12.0**0.5

    def guard_bounds(self) -> dict:
        """The soft bounds as ``immnet.imm.RangeGuard``'s fields (``RangeGuard(**spec.guard_bounds())``): the range
        bounds, the bound turn's rate, the radial share at which it clears (its heading back by
        ``bound_clear_heading_deg``: sin 30 deg = 0.5, to 12 digits) and a CA segment's speed bounds."""
        return {"outer": self.bound_range_outer, "inner": self.bound_range_inner, "rate_deg": self.bound_turn_rate_deg,
                "clear_share": round(math.sin(math.radians(self.bound_clear_heading_deg)), 12),
                "speed_min": self.bound_speed_min,
                "speed_max": self.bound_speed_max, "vz_max": self.bound_vz}

    # --- dict / YAML --------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """Every field; those of the plots only where not their defaults (a spec without plots keeps the meta.json
        it had before plots existed)."""
        d = dataclasses.asdict(self)
        for name in PLOT_FIELDS:
            if d[name] == _DEFAULTS[name]:
                del d[name]
        return d

    @classmethod
    def from_dict(cls, d: dict | None) -> "DataSpec":
        """Defaults overridden by ``d``; an unknown field is a ``ValueError`` naming it."""
        d = dict(d or {})
        names = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - set(names))
        if unknown:
            raise ValueError(f"unknown DataSpec field(s) {unknown}; valid fields: {sorted(names)}")
        out = {}
        for k, v in d.items():
            typ = int if names[k].type in ("int", int) else float
            try:
                out[k] = typ(v)
            except (TypeError, ValueError):
                raise ValueError(f"DataSpec field {k!r} needs a number, got {v!r}") from None
        return cls(**out)

    @classmethod
    def from_yaml(cls, path: str | Path) -> "DataSpec":
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"data config not found: {path}")
        d = yaml.safe_load(path.read_text()) or {}
        if not isinstance(d, dict):
            raise ValueError(f"{path}: a data config is a mapping of DataSpec fields")
        return cls.from_dict(d)


def check_numbers(spec) -> None:
    """A ValueError naming the first field of the dataclass ``spec`` (``DataSpec``, ``RealSpec``, ``SceneSpec``) that
    is not a finite number (not a bool), or a tuple or list of them."""
    for f in dataclasses.fields(spec):
        v = getattr(spec, f.name)
        if not all(isinstance(x, numbers.Real) and not isinstance(x, bool) and math.isfinite(x)
                   for x in (v if isinstance(v, (tuple, list)) else (v,))):
            raise ValueError(f"{type(spec).__name__} field {f.name!r} must be a finite number, got {v!r}")


PLOT_PAIRS = {"sigma_range": "", "sigma_azimuth": "_deg", "sigma_elevation": "_deg"}
"""The plots' std pairs: ``{name}_min{unit}`` and ``{name}_max{unit}`` fields of :class:`DataSpec`."""
PLOT_FIELDS = (*(f"{n}_{end}{u}" for n, u in PLOT_PAIRS.items() for end in ("min", "max")), "outliers",
               "outlier_scale")
_DEFAULTS = {f.name: f.default for f in dataclasses.fields(DataSpec)}
