"""Ship a trained IMMNet: strip a Lightning checkpoint to its weights and hyperparameters.

    python -m immnet.training.export CKPT OUT.ckpt

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
    src = load_checkpoint(ckpt)
    if not (isinstance(src.get("state_dict"), dict) and isinstance(src.get("hyper_parameters"), dict)):
        raise ValueError(f"{ckpt} is not a Lightning checkpoint of an IMMNet module")
    net = net_arguments(src["hyper_parameters"].get("net"))  # the network's arguments, in either config form
    # the model set inline, so that the file works without this repository's configs/
    net["model_set"] = ModelSet.from_config(net.get("model_set", "configs/model_sets/imm4.yaml")).to_config()["models"]
    net.update(settings)
    slim = add_checksum({
        "state_dict": {k: v for k, v in src["state_dict"].items() if k.startswith("net.")},
        "hyper_parameters": {"net": net},
        "global_step": src.get("global_step"),
    })
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with publishing(out) as tmp:
        torch.save(slim, tmp)
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ckpt")
    parser.add_argument("out")
    a = parser.parse_args()
    print(export_weights(a.ckpt, a.out))
