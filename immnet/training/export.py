"""Ship a trained IMMNet: strip a Lightning checkpoint to its weights and hyperparameters.

    python -m immnet.training.export CKPT OUT.ckpt
    python -m immnet.training.export --join CKPT CKPT [CKPT ...] OUT.ckpt   # output corrections on one filter

The file keeps ``state_dict`` and ``hyper_parameters`` (what ``Tracker.from_checkpoint`` reads),
without optimizer state, with the checksum of its weights (``immnet.checkpoints``, docs/checkpoints.md),
and is written to a temporary name renamed when complete. The source is read as plain data and its own
checksum, if it has one, verified; the weights are copied unchanged.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from immnet.checkpoints import add_checksum, load_checkpoint
from immnet.data.scratch import publishing
from immnet.motion import ModelSet
from immnet.stages.network import net_arguments


OUTPUT_SETTINGS = ("cov_consistency",)
"""``IMMNet`` arguments that change what a network reports, not its weights or what it estimates: settable at export."""


def export_weights(ckpt: str | Path, out: str | Path, settings: dict | None = None) -> Path:
    """``settings``: ``OUTPUT_SETTINGS`` to set in the exported network's arguments (e.g. a covariance consistency
    chosen on validation data after training); anything else is refused, so the weights keep their training."""
    settings = dict(settings or {})
    bad = sorted(set(settings) - set(OUTPUT_SETTINGS))
    if bad:
        raise ValueError(f"export sets only {', '.join(OUTPUT_SETTINGS)}, not {', '.join(bad)}")
    src, net, state = _read(ckpt)
    net.update(settings)
    return _write({"state_dict": state, "hyper_parameters": {"net": net}, "global_step": src.get("global_step")}, out)


def _read(ckpt) -> tuple[dict, dict, dict]:
    """``ckpt`` read as plain data, its network's arguments (either config form; the model set inline, so that the
    file works without this repository's configs/) and its network's weights (``net.``-prefixed)."""
    src = load_checkpoint(ckpt)
    if not (isinstance(src.get("state_dict"), dict) and isinstance(src.get("hyper_parameters"), dict)):
        raise ValueError(f"{ckpt} is not a Lightning checkpoint of an IMMNet module")
    net = net_arguments(src["hyper_parameters"].get("net"), saved=True)
    net["model_set"] = ModelSet.from_config(net.get("model_set", "configs/model_sets/imm4.yaml")).to_config()["models"]
    return src, net, {k: v for k, v in src["state_dict"].items() if k.startswith("net.")}


def _write(slim: dict, out) -> Path:
    """``slim`` with the checksum of its weights, written to ``out`` under a temporary name renamed when complete."""
    add_checksum(slim)
    out = Path(out)
    with publishing(out) as tmp:
        torch.save(slim, tmp)
    return out


ENSEMBLE = "immnet.stages.correct.CorrectionEnsemble"
SINGLE = "immnet.stages.correct.OutputCorrection"


def join_corrections(ckpts, out: str | Path) -> Path:
    """One network of ``ckpts``' output corrections on their common filter (``CorrectionEnsemble``): each a
    checkpoint (a run's, or exported weights) of the same network with one ``OutputCorrection``, trained as a run of
    its own. Everything but the correction must be the same in all of them, arguments and weights, to the bit (the
    filters run once for all the members): a ValueError naming what differs, and nothing written, otherwise."""
    ckpts = [Path(c) for c in ckpts]
    if len(ckpts) < 2:
        raise ValueError(f"joining corrections needs at least 2 checkpoints, got {len(ckpts)}")
    nets, states = [], []
    for ckpt in ckpts:
        _, net, state = _read(ckpt)
        correction = net.pop("correction", None) or {}
        if correction.get("class_path") != SINGLE:
            raise ValueError(f"{ckpt}: its network has no single output correction ({SINGLE}) to join")
        net["correction_args"] = dict(correction.get("init_args") or {})  # hidden, layers: the same in every member
        nets.append(net)
        states.append(state)
    for ckpt, net, state in zip(ckpts[1:], nets[1:], states[1:]):
        differ = sorted(k for k in set(net) | set(nets[0]) if net.get(k) != nets[0].get(k))
        if differ:
            raise ValueError(f"{ckpt} is not the network of {ckpts[0]} with another correction: "
                             f"{', '.join(differ)} differ")
        base = {k for k in states[0] if not k.startswith("net.correct.")}
        if base != {k for k in state if not k.startswith("net.correct.")}:
            raise ValueError(f"{ckpt}: its filters' weights are not named as {ckpts[0]}'s")
        moved = sorted(k for k in base if not torch.equal(state[k], states[0][k]))
        if moved:
            raise ValueError(f"{ckpt}: its weights outside the correction differ from {ckpts[0]}'s "
                             f"({', '.join(moved[:3])}{', ...' if len(moved) > 3 else ''}): its filters learned too")
    net = dict(nets[0])
    args = net.pop("correction_args")
    net["correction"] = {"class_path": ENSEMBLE, "init_args": {"members": len(ckpts), **args}}
    joined = {k: v for k, v in states[0].items() if not k.startswith("net.correct.")}
    for i, state in enumerate(states):
        joined.update({f"net.correct.members.{i}.{k[len('net.correct.'):]}": v
                       for k, v in state.items() if k.startswith("net.correct.")})
    return _write({"state_dict": joined, "hyper_parameters": {"net": net}, "global_step": None}, out)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ckpt", nargs="+", help="one checkpoint to export; several with --join")
    parser.add_argument("out")
    parser.add_argument("--join", action="store_true",
                        help="join the output corrections of several runs on one filter into one network")
    a = parser.parse_args()
    if not a.join and len(a.ckpt) > 1:
        parser.error("several checkpoints: --join them, or export one")
    print(join_corrections(a.ckpt, a.out) if a.join else export_weights(a.ckpt[0], a.out))
