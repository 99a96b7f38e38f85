"""Lightning's checkpoint reads through the package's safe reader (docs/checkpoints.md).

``SafeCheckpointIO`` is the default ``trainer.plugins`` of ``immnet fit|validate|test``
(``immnet.training.cli``): ``--ckpt_path`` (a path, ``last`` or ``best``) is read by
``immnet.checkpoints.load_checkpoint`` (``weights_only=True`` whatever the caller asks, checksum
verified), so a resumed or evaluated checkpoint never runs code from the file. Writing is Lightning's.
"""

from __future__ import annotations

from pathlib import Path

from lightning.pytorch.plugins.io import TorchCheckpointIO

from immnet.checkpoints import CheckpointError, load_checkpoint


class SafeCheckpointIO(TorchCheckpointIO):
    """``TorchCheckpointIO`` whose reads are plain data only (``weights_only`` is ignored: always True)."""

    def load_checkpoint(self, path, map_location=None, weights_only=None) -> dict:
        return load_checkpoint(Path(path), map_location=map_location if map_location is not None else "cpu")


def check_checkpoints(config) -> None:
    """Read the checkpoint files a parsed LightningCLI config names (``ckpt_path``, and the model's
    ``stage1_checkpoint`` / ``init_checkpoint`` / ``init_parameters``) before anything is built from them: LightningCLI reads
    ``ckpt_path``'s hyperparameters itself, and an error inside the model's constructor reaches the user
    as jsonargparse's traceback. A refused file raises ``CheckpointError`` (one line, naming the file)."""
    sub = config.get("subcommand")
    if not sub:
        return
    path = config[sub].get("ckpt_path")
    if path and Path(path).is_file():  # not "last" / "best", which the trainer resolves and reads through SafeCheckpointIO
        load_checkpoint(path)
    init = (config[sub].get("model") or {}).get("init_args") or {}
    for arg in ("stage1_checkpoint", "init_checkpoint", "init_parameters"):
        path = init.get(arg)
        if path and not Path(path).is_file():
            raise CheckpointError(f"model.init_args.{arg}: checkpoint not found: {path}")
        if path:
            load_checkpoint(path)
