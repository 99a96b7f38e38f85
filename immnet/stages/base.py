"""What a stage is: a ``TensorDictModuleBase`` over the key vocabulary of ``immnet.keys``.

A tracker step is a ``TensorDictSequential`` of five stages (predict, gain, update, classify, fuse; filter
experts' interaction before the predict), between a track start's two (``immnet.stages.start``).
Tensors are ``[B, ...]`` for a fused quantity and ``[B, M, ...]`` for one per expert. In stage-1
training each expert runs alone on its own trajectories, so the "fused" state is itself
``[B, M, 9]``; ``per_expert`` lets every stage accept both.

Each stage tells the truth about itself (docs/stages.md; ``tests/test_stage_contract.py`` holds it to it):

* ``in_keys`` / ``out_keys``: exactly what this instance, as configured, reads and writes;
* ``set_keys(**names)``: renames its keys (TorchRL's ``set_keys``), by the lower-case names of
  ``immnet.keys`` (``fused=("track", "x")``); the stage reads and writes the new names;
* ``wire(upstream)``: told what the stages before it in the step write, a stage whose inputs depend
  on them declares them (a Bayesian mode update reads the guarded transition matrix where the
  interaction writes one);
* ``carry_spec(batch, experts_alone, dtype, device)``: the state it carries from one scan to the
  next, with its value for a track that has not started (TorchRL's primer), and
  ``start_carry(carry, z, x, second)`` its value after a track's first or second detection (``start_estimate``: a
  prior it adds to the start estimate ``x`` before);
* ``for_experts_alone()``: the stage as stage 1 runs it (each expert alone), where its keys differ.
"""

from __future__ import annotations

import functools

import torch
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import unravel_key

from immnet import keys
from immnet.motion import POS_VIEW, ModelSet

KEY_NAMES = {
    name.lower(): unravel_key(value)
    for name, value in vars(keys).items()
    if name.isupper() and isinstance(value, (str, tuple))
}
"""``set_keys``'s vocabulary: the lower-case name of each key constant of ``immnet.keys``."""


def _renaming(body):
    """``forward`` that runs ``body`` under the default key names where ``set_keys`` renamed some."""

    @functools.wraps(body)
    def forward(self, td, *args, **kwargs):
        renamed = self._renamed
        if not renamed or self._under_defaults:
            return body(self, td, *args, **kwargs)
        present = set(td.keys(True))
        stash = {d: td.pop(d) for d in renamed if d in present}  # a default name used for something else
        for default, custom in renamed.items():
            if custom in present:
                td.set(default, td.pop(custom))
        self._under_defaults = True
        try:
            td = body(self, td, *args, **kwargs)
        finally:
            self._under_defaults = False
        present = set(td.keys(True))
        for default, custom in renamed.items():
            if default in present:
                td.set(custom, td.pop(default))
        for default, value in stash.items():
            td.set(default, value)
        return td

    forward._renaming = True
    return forward


def scan_interval(td, nominal: float):
    """This scan's interval: ``("interval")`` ``[B]`` where the step carries it (the optional input of a step,
    docs/stages.md), else the ``nominal`` float. Returns ``(dt, per_track)``: ``dt`` a float or ``[B, 1]``
    (broadcasting against ``[B, M]``)."""
    d = td.get(keys.INTERVAL, None)
    return (nominal, False) if d is None else (d.unsqueeze(-1), True)


class Stage(TensorDictModuleBase):
    """A stage built for a model set of ``M`` experts."""

    in_keys: list = []
    out_keys: list = []
    shared: tuple[str, ...] = ()
    """The settings of ``IMMNet`` (``p_stay``, ``guard``, ``modes``: what the interaction and the mode update must
    agree on) this stage takes: ``IMMNet`` hands each of them to the stage in place of its own value."""
    load_options: tuple[str, ...] = ()
    """Its settings that hold no weights and that ``immnet.tracking.load_network`` may set on a trained stage
    (a gain's ``guard``, ``adapt``, ``r``, ``reacquire``)."""

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        body = cls.__dict__.get("forward")
        if body is not None and not getattr(body, "_renaming", False):
            cls.forward = _renaming(body)

    def __init__(self, model_set: ModelSet | None = None):
        super().__init__()
        self.model_set = model_set
        self.n_experts = len(model_set) if model_set is not None else 1
        self._renamed: dict = {}  # default key -> this instance's name for it (set_keys)
        self._under_defaults = False

    # --- keys ---------------------------------------------------------------------------------
    def set_keys(self, **names) -> "Stage":
        """Rename this stage's keys: ``name=new_key`` with ``name`` a lower-case key name of
        ``immnet.keys`` among this stage's keys; returns the stage."""
        mine = {unravel_key(k) for k in (*self.in_keys, *self.out_keys)}
        current = {self._renamed.get(d, d): d for d in KEY_NAMES.values()}
        for name, new in names.items():
            if name not in KEY_NAMES:
                raise ValueError(f"{type(self).__name__}.set_keys: no key named {name!r} in immnet.keys")
            default = KEY_NAMES[name]
            old = self._renamed.get(default, default)
            if old not in mine:
                raise ValueError(f"{type(self).__name__}.set_keys: {name!r} ({default}) is not one of its keys")
            new = unravel_key(new)
            if new in current and current[new] != default:
                raise ValueError(f"{type(self).__name__}.set_keys: {new} is already the key of {current[new]}")
            self.in_keys = [new if unravel_key(k) == old else k for k in self.in_keys]
            self.out_keys = [new if unravel_key(k) == old else k for k in self.out_keys]
            if new == default:
                self._renamed.pop(default, None)
            else:
                self._renamed[default] = new
        return self

    def wire(self, upstream: set) -> None:
        """Told the keys the stages before it in a step write (default names); by default nothing changes."""

    def for_experts_alone(self) -> "Stage":
        """This stage as stage 1 runs it, each expert alone; itself where its keys are the same."""
        return self

    # --- its learned weights ----------------------------------------------------------------------
    knock_out = None
    """A stage whose learned part corrects a model-based base: the method that sets that correction to zero, the
    rest as trained (``IMMNet.knock_out``); None for a stage without one."""

    def interval_columns(self) -> dict[str, int]:
        """The weights that read the interval input (``log(interval / dt)``) and its column (``IMMNet``'s); none."""
        return {}

    def group_rows(self) -> dict[str, int]:
        """The weights whose rows are one block per group of modes and the number of groups (``IMMNet``'s); none."""
        return {}

    # --- the carry ------------------------------------------------------------------------------
    def carry_spec(self, batch: int, experts_alone: bool = False, dtype=torch.float32, device=None) -> dict:
        """The keys this stage carries from one scan to the next, each with its value for ``batch``
        tracks that have not started (``[B, ...]``, or ``[B, M, ...]`` per expert and experts alone)."""
        return {}

    def start_carry(self, carry, z: torch.Tensor, x: torch.Tensor, second: bool) -> dict:
        """The carried keys that a track's first (``second=False``) or second detection ``z`` sets
        (start estimate ``x``), from the ``carry`` before it; the others take ``carry_spec``'s value."""
        return {}

    def start_estimate(self, carry, z: torch.Tensor, x: torch.Tensor, second: bool) -> torch.Tensor:
        """The start estimate ``x`` after a track's first or second detection ``z`` with what this stage knows of a
        starting track beside its detections (a filter gain's prior on the vertical speed), before any stage's
        ``start_carry`` reads it: ``x`` itself unless a stage knows more."""
        return x


def per_expert(x: torch.Tensor, n_experts: int, event_dims: int = 1) -> torch.Tensor:
    """``[B, *event]`` broadcast to ``[B, M, *event]``; ``[B, M, *event]`` is returned as is."""
    if x.dim() == 1 + event_dims:
        return x.unsqueeze(1).expand(x.shape[0], n_experts, *x.shape[1:])
    return x


def track_where(cond: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``where(cond, a, b)`` with a track mask ``cond [B]`` broadcast over ``b``'s other dimensions, in ``b``'s dtype."""
    return torch.where(cond.view(-1, *([1] * (b.dim() - 1))), a.to(b.dtype), b)


def step_input(td, key) -> torch.Tensor:
    """The step's input ``key`` ``[B]`` (``immnet.stages.start.STEP_INPUTS``); where the step has none, a ValueError
    saying what to give: each track's measurement std ``"r"`` or each detection's covariance ``"meas_cov"`` for a
    filter gain told it (``r="data"``, ``r="detection"``), the truth's ``("truth", ...)`` for an oracle."""
    value = None if td is None else td.get(key, None)
    if value is not None:
        return value
    if key == keys.R:
        raise ValueError("this step's filter gain is told each track's measurement std (r='data'): give the step its "
                         "input 'r' [B] (IMMNet.rollout(..., r=...), IMMNet.scan(..., r=...))")
    if key == keys.MEAS_COV:
        raise ValueError("this step's filter gain is told each detection's measurement covariance (r='detection'): "
                         f"give the step its input {key!r} [B, 3, 3] (IMMNet.rollout(..., meas_cov=...), "
                         "IMMNet.scan(..., meas_cov=...))")
    raise ValueError(f"this step reads the truth's {key[-1]!r} at each scan (an oracle: the clairvoyant filters' "
                     f"configuration): give the step its input {key} [B] (IMMNet.rollout(..., truth=...), "
                     "IMMNet.scan(..., truth=...))")


def group_ids(groups, like: torch.Tensor) -> torch.Tensor:
    """The group of each coordinate (``immnet.motion.MODE_GROUPS``) as a tensor on ``like``'s device: a stage's buffer
    as it is (no copy on the step's hot path), a tuple made one."""
    return torch.as_tensor(groups, device=like.device)


def coordinate_weights(mu: torch.Tensor, n: int, groups=None) -> torch.Tensor:
    """The weight of each expert on each of ``n`` state coordinates: mode probabilities ``mu [B, M]`` as
    ``[B, M, 1]``, or modes per group ``mu [B, G, M]`` as ``[B, M, n]`` (each coordinate its group's, ``groups``:
    ``immnet.motion.MODE_GROUPS``, a tuple or a tensor)."""
    if mu.dim() == 2:
        return mu.unsqueeze(-1)
    return mu.index_select(1, group_ids(groups, mu)[:n]).transpose(1, 2)


def block_weights(mu: torch.Tensor, n: int, groups=None) -> torch.Tensor:
    """The weight of each expert on each entry of an ``n x n`` covariance: ``[B, M, 1, 1]`` for ``mu [B, M]``; for
    modes per group ``mu [B, G, M]``, ``[B, M, n, n]`` with each group's block its group's probability and 0 across
    groups (the groups' IMMs are independent: their cross-covariances are not kept)."""
    if mu.dim() == 2:
        return mu[..., None, None]
    g = group_ids(groups, mu)[:n]
    same = (g[:, None] == g[None, :]).to(mu.dtype)
    return coordinate_weights(mu, n, groups).unsqueeze(-1) * same


def axis_probs(mu: torch.Tensor, groups) -> torch.Tensor:
    """Modes per group ``mu [..., G, M]`` as each Cartesian axis's, ``[..., 3, M]`` (an axis's are its position's
    group's; ``groups`` a tuple or a tensor): what the data modes and the reported covariance's scale average over,
    so that an axis counts once."""
    return mu.index_select(-2, group_ids(groups, mu)[POS_VIEW])


def measured(z: torch.Tensor) -> torch.Tensor:
    """Mask of rows holding a measurement (no NaN component), shape ``z.shape[:-1] + (1,)``."""
    return ~torch.isnan(z).any(dim=-1, keepdim=True)
