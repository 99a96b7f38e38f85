"""What a method is, and building one by name.

A method is any object with ``name: str``, ``needs: tuple[str, ...]`` (data keys it reads beyond
``measurements``) and ``track(batch: TensorDict[B]) -> TensorDict[B]`` holding ``state [B, T, 9]``
and, where it has them, ``mode_probs [B, T, 4]`` over the data modes. An optional
``check(data)`` raises a ValueError for data the method cannot score (``evaluate`` calls it on the
whole data before running any method: a learned tracker refuses a ``dt`` it was not trained at).

Methods are configured, not coded in: ``configs/methods/<name>.yaml`` holds one ``class_path`` /
``init_args`` mapping, looked for in the working directory's ``configs/methods/`` first (a user's own
or tuned methods), then among the packaged configs (``immnet.config``; docs/configs.md); their names are
``immnet.filters.registry``'s, read without torch for ``immnet evaluate --help``.
``build_method(name, checkpoint)`` loads it; a checkpoint (from the YAML's
``init_args`` or from the caller) reaches the constructor as ``checkpoint=``, and a range guard
(``immnet evaluate --guard``) as ``guard=``. A method may also have ``configure(meta, sigma_q=None)``:
told the data set's ``meta`` (``load_dataset``'s, holding the generator's ``spec`` where the data has
one) before it runs; the clairvoyant references take the data's statistics from it. The only built-in
is ``measurements`` (:class:`RawMeasurements`), which needs no configuration.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Protocol, Sequence, runtime_checkable

import torch
from tensordict import TensorDict

from immnet import keys
from immnet.config import REPO_ROOT, import_class, load_yaml
from immnet.filters.registry import ORDER, configured_methods  # noqa: F401  (ORDER: re-exported, scripts import it)
from immnet.filters.registry import method_dirs as _method_dirs
from immnet.filters.registry import MULTI_TARGET_BANDS, MULTI_TARGET_FILTER
from immnet.filters.base import output
from immnet.imm.guard import AS_CONFIGURED
from immnet.motion import POS

@runtime_checkable
class Method(Protocol):
    """The method protocol (module doc), checked by structure (``immnet.evaluation.Method``)."""

    name: str
    needs: tuple[str, ...]

    def track(self, batch: TensorDict) -> TensorDict: ...


class RawMeasurements:
    """The measurements as an estimate: ``x_hat_t = [z_t, 0, 0]`` per axis (no velocity/acceleration).

    A missing detection (NaN) takes the last valid measurement. Before a track's first detection
    there is nothing to report: the estimate is NaN there (throughout, for a track never
    detected), as for every tracker (docs/evaluation.md: those scans are not scored).
    """

    name = "measurements"
    needs: tuple[str, ...] = ()

    def track(self, batch: TensorDict) -> TensorDict:
        z = batch[keys.MEASUREMENTS]
        B, T, _ = z.shape
        valid = ~torch.isnan(z).any(dim=-1)  # [B, T]
        t = torch.arange(T, device=z.device).expand(B, T)
        idx = torch.where(valid, t, torch.zeros_like(t)).cummax(dim=-1).values
        filled = torch.gather(z, 1, idx.unsqueeze(-1).expand(B, T, 3))
        state = z.new_zeros(B, T, 9)
        state[..., list(POS)] = filled
        return output(state, measurements=z)


BUILTIN = {RawMeasurements.name: RawMeasurements}


def method_config(name: str, methods_dir: Path | None = None) -> Path:
    """The YAML of method ``name``: in ``methods_dir`` when given, else the first of the working
    directory's ``configs/methods/`` and the packaged ones that has it; ``ValueError`` listing where
    it looked and the methods there are."""
    paths = list(dict.fromkeys(d.absolute() / f"{name}.yaml" for d in _method_dirs(methods_dir)))
    for path in paths:
        if path.is_file():
            return path
    if name == MULTI_TARGET_FILTER:
        raise ValueError(f"{name} is the multi-target tracker's per-track filter (plots without a track_id), the IMM "
                         f"tuned at the scan interval: name one of its IMMs here "
                         f"({', '.join(m for _, m in MULTI_TARGET_BANDS)})")
    raise ValueError(f"unknown method {name!r} (no {' or '.join(map(str, paths))}); "
                     f"available: {', '.join(available_methods(methods_dir))}")


def _method_class(name: str, methods_dir: Path | None = None):
    """``(class, init_args)`` of a method; ``ValueError`` naming the method when it cannot be had."""
    if name in BUILTIN:
        return BUILTIN[name], {}
    path = method_config(name, methods_dir)
    spec = load_yaml(path) or {}
    if not isinstance(spec, dict) or "class_path" not in spec:
        raise ValueError(f"method {name!r}: {path} holds no 'class_path' mapping")
    try:
        cls = import_class(spec["class_path"])
    except ValueError as err:
        others = [m for m in available_methods(methods_dir) if m != name]
        raise ValueError(f"method {name!r} is not available ({err}); available: {', '.join(others)}") from None
    return cls, dict(spec.get("init_args") or {})


def available_methods(methods_dir: Path | None = None) -> list[str]:
    """Configured methods whose class imports, in table order."""
    out = []
    for name in configured_methods(methods_dir):
        try:
            if name not in BUILTIN:
                import_class((load_yaml(method_config(name, methods_dir)) or {})["class_path"])
        except Exception:  # noqa: BLE001 - anything that stops the import makes it unavailable
            continue
        out.append(name)
    return out


def build_options(cls) -> dict:
    """What ``build_method`` may set on a method class's constructor, with its defaults (``Method.build_options``;
    none for a class that declares none)."""
    return getattr(cls, "build_options", {})


def takes_checkpoint(name: str, methods_dir: Path | None = None) -> bool:
    """Whether a method is built from a checkpoint (its YAML names one, or its class takes one)."""
    cls, init_args = _method_class(name, methods_dir)
    return "checkpoint" in init_args or "checkpoint" in build_options(cls)


def gives_cov(name: str, methods_dir: Path | None = None) -> bool:
    """Whether a method can give its state's covariance ``state_cov`` (its class takes ``return_cov``)."""
    cls, _ = _method_class(name, methods_dir)
    return "return_cov" in build_options(cls)


def build_method(name: str, checkpoint: str | Path | None = None, methods_dir: Path | None = None, guard=AS_CONFIGURED,
                 return_cov: bool = False, told_r: bool = False):
    """The method configured as ``configs/methods/<name>.yaml`` (or a built-in), ready to ``track``.

    ``checkpoint`` overrides the YAML's ``init_args.checkpoint``; a relative checkpoint path in
    the YAML is read from the working directory, else from the directory above the package (the
    checkout, or ``site-packages``: ``immnet/pretrained/...`` works in both). The object's
    ``name`` is set to ``name`` so that rows carry the registry name.

    The options below reach a class's constructor where it declares them (``Method.build_options``).
    ``guard`` (``immnet.imm.guard.parse_guard``'s: ``"checkpoint"``, ``None`` or ``{"outer", "inner"}``)
    replaces the range guard (``immnet.imm.guard``) of every method that has one: a class taking
    ``guard`` whose configured value is not off (IMMNet's ``"checkpoint"``, imm-ekf-guard's ``true``). A
    method configured without a guard (imm-ekf) keeps none: ``--guard none`` makes imm-ekf-guard its
    unguarded twin, never the reverse.

    ``return_cov``: a method that can give its state's covariance (:func:`gives_cov`) is built to give it,
    ``state_cov [B, T, 9, 9]`` in its output; the others are built as configured and give none.

    ``told_r``: a trained network whose filter experts' r can be set (a constructor taking a ``checkpoint`` and an
    ``r``: ``IMMNetMethod``) is told each track's measurement std from the data (``r="data"``), as the model-based
    filters for real flights are, in place of estimating it; the other methods are as configured.
    """
    cls, init_args = _method_class(name, methods_dir)
    options = build_options(cls)
    if told_r and {"checkpoint", "r"} <= set(options):
        init_args["r"] = "data"
    if return_cov and "return_cov" in options:
        init_args["return_cov"] = True
    if not (isinstance(guard, str) and guard == AS_CONFIGURED):
        if "guard" in options and init_args.get("guard", options["guard"]) not in (None, False):
            init_args["guard"] = guard
    if checkpoint is not None:
        if "checkpoint" not in init_args and "checkpoint" not in options:
            raise ValueError(f"method {name!r} ({cls.__name__}) does not take a checkpoint")
        init_args["checkpoint"] = str(checkpoint)
    ckpt = init_args.get("checkpoint")
    if ckpt is not None and not Path(ckpt).exists():
        if (REPO_ROOT / ckpt).exists():
            init_args["checkpoint"] = str(REPO_ROOT / ckpt)
        else:
            raise FileNotFoundError(f"method {name!r}: checkpoint not found: {ckpt}")
    method = cls(**init_args)
    with contextlib.suppress(AttributeError):  # a read-only property: keep the method's own name
        method.name = name
    return method


def missing_keys(method, data_keys: Sequence[str]) -> list[str]:
    """The data arrays a method needs that ``data_keys`` lack."""
    have = set(data_keys)
    return [k for k in (keys.MEASUREMENTS, *getattr(method, "needs", ())) if k not in have]
