"""``immnet fit|validate|test``: Lightning's CLI over the tracker modules and the 3D-LAST DataModule.

A recipe is a LightningCLI config (``class_path`` / ``init_args``; ``--print_config`` prints it).
A recipe may also chain runs: a top-level ``stages:`` list of such configs runs them in order and
hands each run's best checkpoint to the next as ``model.init_args.stage1_checkpoint`` (stage 1,
then stage 2). A stage written ``{config: PATH, checkpoint_as: init_checkpoint}`` takes it under that
argument instead (a fine-tune of the whole IMMNet after stage 2). W&B is the default logger, offline unless ``WANDB_MODE=online``.

Each stage of a chain runs as its own ``immnet fit`` process, and every run leaves its own command
line in ``sys.argv``: Lightning's DDP launcher starts its workers by re-running that command, so a
worker runs exactly one stage, and the next stage launches its workers afresh.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import lightning as L
import yaml
from lightning.pytorch.cli import LightningCLI

from immnet.config import resolve_path
from immnet.training.checkpoint_io import check_checkpoints

_RESULT_ENV = "IMMNET_FIT_RESULT"
"""Where a ``fit`` run started by a chain writes its best checkpoint's path (rank 0 only)."""


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
        # LASTDataModule shards its batches per rank itself (its samplers are batch samplers);
        # checkpoints are read as plain data with their checksum verified (docs/checkpoints.md)
        parser.set_defaults({"trainer.logger": _default_logger(), "trainer.use_distributed_sampler": False,
                             "trainer.plugins": [{"class_path": "immnet.training.checkpoint_io.SafeCheckpointIO"}]})

    def parse_arguments(self, parser, args):
        super().parse_arguments(parser, args)
        check_checkpoints(self.config)


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


def stage_entry(stage, i: int) -> tuple[str | dict, str]:
    """A chain's ``i``-th entry (0-based) as ``(config, checkpoint_as)``: ``config`` a path or an inline
    config, ``checkpoint_as`` the argument that receives the previous stage's checkpoint."""
    arg = "stage1_checkpoint"
    if isinstance(stage, dict) and "config" in stage:  # {config: PATH, checkpoint_as: ARG}
        if set(stage) - {"config", "checkpoint_as"} or not isinstance(stage["config"], str):
            raise ValueError(f"stage {i + 1}: a stage with `config:` takes only `config` (a path) and `checkpoint_as`, got {sorted(stage)}")
        arg = stage.get("checkpoint_as", arg)
        if arg not in ("stage1_checkpoint", "init_checkpoint"):
            raise ValueError(f"stage {i + 1}: checkpoint_as must be stage1_checkpoint or init_checkpoint, got {arg!r}")
        stage = stage["config"]
    return stage, arg


def run_stages(recipe: dict, extra: list[str]) -> str:
    """Run a chained recipe, each stage in its own process; returns the last run's best checkpoint."""
    ckpt = None
    n = len(recipe["stages"])
    for i, stage in enumerate(recipe["stages"]):
        stage, arg = stage_entry(stage, i)
        with tempfile.TemporaryDirectory(prefix="immnet-stage-") as tmp:
            if isinstance(stage, str):
                path = str(resolve_path(stage))
            else:
                path = str(Path(tmp) / "stage.yaml")
                Path(path).write_text(yaml.safe_dump(stage))
            cmd = [sys.executable, "-m", "immnet.cli", "fit", "--config", path, *extra]
            if ckpt is not None:
                cmd += [f"--model.init_args.{arg}", ckpt]
            print(f"[immnet fit] stage {i + 1}/{n}: {path}", file=sys.stderr, flush=True)
            result = Path(tmp) / "best"
            done = subprocess.run(cmd, env={**os.environ, _RESULT_ENV: str(result)})
            if done.returncode != 0:
                raise SystemExit(f"[immnet fit] stage {i + 1}/{n} ({path}) failed with exit code {done.returncode}")
            ckpt = result.read_text().strip() if result.is_file() else ""
        if not ckpt:
            raise RuntimeError(f"stage {i + 1} left no checkpoint (is a ModelCheckpoint configured?)")
        print(f"[immnet fit] stage {i + 1} checkpoint: {ckpt}", file=sys.stderr, flush=True)
    return ckpt


def _run(argv: list[str]) -> IMMNetCLI:
    """One Lightning run; ``sys.argv`` becomes its command line (what a DDP launcher re-runs)."""
    saved, sys.argv = sys.argv, [sys.argv[0], *argv]
    try:
        cli = _cli(argv)
    finally:
        sys.argv = saved
    out = os.environ.get(_RESULT_ENV)
    if out and argv[0] == "fit" and cli.trainer.is_global_zero:
        callback = cli.trainer.checkpoint_callback
        best = (callback.best_model_path or callback.last_model_path) if callback else ""
        Path(out).write_text(best or "")
    return cli


def lightning_main(argv: list[str]) -> None:
    """Run Lightning's CLI; a first ``--config`` holding ``stages:`` runs the chain, and every
    further argument (another ``--config`` too, e.g. an ablation) applies to each stage."""
    config = _config_arg(argv)
    if argv[0] == "fit" and config is not None:
        recipe = yaml.safe_load(resolve_path(config).read_text())
        if isinstance(recipe, dict) and "stages" in recipe:
            i = argv.index("--config") if "--config" in argv else argv.index(f"--config={config}")
            width = 2 if argv[i] == "--config" else 1
            run_stages(recipe, argv[1:i] + argv[i + width :])
            return
    _run(argv)
