"""``immnet fit|validate|test``: Lightning's CLI over the tracker modules and the 3D-LAST DataModule.

A recipe is a LightningCLI config (``class_path`` / ``init_args``; ``--print_config`` prints it).
A recipe may also chain runs: a top-level ``stages:`` list of such configs runs them in order and
hands each run's best checkpoint to the next as ``model.init_args.stage1_checkpoint`` (stage 1,
then stage 2). W&B is the default logger, offline unless ``WANDB_MODE=online``.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import lightning as L
import yaml
from lightning.pytorch.cli import LightningCLI

from immnet.config import resolve_path


def _default_logger() -> dict:
    return {
        "class_path": "lightning.pytorch.loggers.WandbLogger",
        "init_args": {
            "project": "immnet",
            "save_dir": "runs",
            "offline": os.environ.get("WANDB_MODE", "offline") != "online",
        },
    }


class IMMNetCLI(LightningCLI):
    def add_arguments_to_parser(self, parser):
        parser.set_defaults({"trainer.logger": _default_logger()})


def _cli(args: list[str]) -> IMMNetCLI:
    from immnet.data.datamodule import LASTDataModule

    os.environ.setdefault("WANDB_SILENT", "true")
    return IMMNetCLI(
        L.LightningModule,
        LASTDataModule,
        subclass_mode_model=True,
        args=args,
        save_config_kwargs={"overwrite": True},
        auto_configure_optimizers=False,
    )


def _config_arg(argv: list[str]) -> str | None:
    for i, a in enumerate(argv):
        if a == "--config" and i + 1 < len(argv):
            return argv[i + 1]
        if a.startswith("--config="):
            return a.split("=", 1)[1]
    return None


def run_stages(recipe: dict, extra: list[str]) -> str:
    """Run a chained recipe; returns the last run's best checkpoint."""
    ckpt = None
    for i, stage in enumerate(recipe["stages"]):
        if isinstance(stage, str):
            stage = yaml.safe_load(resolve_path(stage).read_text())
        with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as f:
            yaml.safe_dump(stage, f)
        args = ["fit", "--config", f.name, *extra]
        if ckpt is not None:
            args += ["--model.init_args.stage1_checkpoint", ckpt]
        print(f"[immnet fit] stage {i + 1}/{len(recipe['stages'])}", file=sys.stderr, flush=True)
        cli = _cli(args)
        Path(f.name).unlink(missing_ok=True)
        callback = cli.trainer.checkpoint_callback
        ckpt = callback.best_model_path or callback.last_model_path if callback else None
        if not ckpt:
            raise RuntimeError(f"stage {i + 1} left no checkpoint (is a ModelCheckpoint configured?)")
        print(f"[immnet fit] stage {i + 1} checkpoint: {ckpt}", file=sys.stderr, flush=True)
    return ckpt


def lightning_main(argv: list[str]) -> None:
    config = _config_arg(argv)
    if argv[0] == "fit" and config is not None:
        recipe = yaml.safe_load(resolve_path(config).read_text())
        if isinstance(recipe, dict) and "stages" in recipe:
            rest = [a for i, a in enumerate(argv[1:], 1) if a != "--config" and argv[i - 1] != "--config" and not a.startswith("--config=")]
            run_stages(recipe, rest)
            return
    _cli(argv)
