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
            path, tmp = str(resolve_path(stage)), None
        else:
            with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as f:
                yaml.safe_dump(stage, f)
            path = tmp = f.name
        args = ["fit", "--config", path, *extra]
        if ckpt is not None:
            args += ["--model.init_args.stage1_checkpoint", ckpt]
        print(f"[immnet fit] stage {i + 1}/{len(recipe['stages'])}", file=sys.stderr, flush=True)
        try:
            cli = _cli(args)
        finally:
            if tmp:
                Path(tmp).unlink(missing_ok=True)
        callback = cli.trainer.checkpoint_callback
        ckpt = callback.best_model_path or callback.last_model_path if callback else None
        if not ckpt:
            raise RuntimeError(f"stage {i + 1} left no checkpoint (is a ModelCheckpoint configured?)")
        print(f"[immnet fit] stage {i + 1} checkpoint: {ckpt}", file=sys.stderr, flush=True)
    return ckpt


def lightning_main(argv: list[str]) -> None:
    """Run Lightning's CLI; a first ``--config`` holding ``stages:`` runs the chain, and every
    further argument (another ``--config`` too, e.g. an ablation) applies to each stage."""
    sys.argv = [sys.argv[0]]  # the arguments travel in ``args``
    config = _config_arg(argv)
    if argv[0] == "fit" and config is not None:
        recipe = yaml.safe_load(resolve_path(config).read_text())
        if isinstance(recipe, dict) and "stages" in recipe:
            i = argv.index("--config") if "--config" in argv else argv.index(f"--config={config}")
            width = 2 if argv[i] == "--config" else 1
            run_stages(recipe, argv[1:i] + argv[i + width :])
            return
    _cli(argv)
