"""``immnet fit|validate|test``: Lightning's CLI over the tracker modules and the 3D-LAST DataModule.

A recipe is a LightningCLI config (``class_path`` / ``init_args``; ``--print_config`` prints it).
A recipe may also chain runs: a top-level ``stages:`` list of such configs runs them in order and
hands each run's best checkpoint to the next as ``model.init_args.stage1_checkpoint`` (stage 1,
then stage 2). A stage written ``{config: PATH, checkpoint_as: init_checkpoint}`` takes it under that
argument instead (a fine-tune of the whole IMMNet after stage 2). W&B is the default logger, offline unless ``WANDB_MODE=online``.

Each stage of a chain runs as its own ``immnet fit`` process, and every run leaves its own command
line in ``sys.argv``: Lightning's DDP launcher starts its workers by re-running that command, so a
worker runs exactly one stage, and the next stage launches its workers afresh.

Crash safety (docs/immnet.md, "Training"): every run saves ``last.ckpt`` beside its best checkpoint
(:class:`immnet.training.callbacks.LastCheckpoint`), ``--ckpt_path last`` resumes from it, and a fresh
run never overwrites an earlier run's checkpoints unless told to (:mod:`immnet.training.resume`). A
run stopped short of its step budget (``max_time``, a callback) is not finished: it says so and exits
with ``resume.STOPPED_SHORT``, and a chain stops there. A chain rerun skips its finished stages and
resumes the unfinished one. A stage's process gets SIGTERM
when the chain's process dies (Linux: ``PR_SET_PDEATHSIG``), and the chain forwards SIGTERM and SIGINT
to it; the stage then saves its last checkpoint and stops. Nothing is written outside the runs'
checkpoint directories: an inline stage config goes to the stage as a YAML string, and its best
checkpoint's path comes back through a pipe.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import lightning as L
import yaml
from lightning.pytorch.cli import LightningCLI

from immnet.config import resolve_path
from immnet.training.checkpoint_io import check_checkpoints

_RESULT_ENV = "IMMNET_FIT_RESULT_FD"
"""The pipe a ``fit`` run started by a chain writes its best checkpoint's path to (rank 0 only)."""


def _default_logger() -> dict:
    """W&B through Lightning's WandbLogger, offline unless ``WANDB_MODE`` is ``online``. Under
    ``WANDB_MODE=disabled`` the logger is not told ``offline`` (which would set ``WANDB_MODE`` to offline
    itself), so that wandb sees ``disabled`` and writes nothing."""
    return {
        "class_path": "lightning.pytorch.loggers.WandbLogger",
        "init_args": {
            "project": "immnet",
            "save_dir": "runs",
            "offline": os.environ.get("WANDB_MODE", "offline") not in ("online", "disabled"),
        },
    }


class IMMNetCLI(LightningCLI):
    def add_arguments_to_parser(self, parser):
        from immnet.training.callbacks import LastCheckpoint

        # LASTDataModule shards its batches per rank itself (its samplers are batch samplers);
        # checkpoints are read as plain data with their checksum verified (docs/checkpoints.md)
        parser.set_defaults({"trainer.logger": _default_logger(), "trainer.use_distributed_sampler": False,
                             "trainer.plugins": [{"class_path": "immnet.training.checkpoint_io.SafeCheckpointIO"}]})
        parser.add_lightning_class_args(LastCheckpoint, "last_checkpoint")  # every run: last.ckpt
        parser.add_argument("--overwrite_checkpoints", type=bool, default=False,
                            help="start afresh over an earlier run's checkpoints (else refused)")

    def parse_arguments(self, parser, args):
        super().parse_arguments(parser, args)
        check_checkpoints(self.config)

    def fit(self, model, **kwargs):
        """``trainer.fit`` after :func:`immnet.training.resume.plan`; a chained stage reports its best checkpoint."""
        from lightning.pytorch.utilities.exceptions import SIGTERMException

        from immnet.training import resume
        from immnet.training.callbacks import LastCheckpoint

        trainer = self.trainer
        report = os.environ.pop(_RESULT_ENV, None)  # before DDP workers copy the environment
        overwrite = bool(self.config[self.subcommand].get("overwrite_checkpoints"))
        ckpt_path = resume.plan(trainer, kwargs.pop("ckpt_path", None), overwrite)
        if isinstance(ckpt_path, resume.Finished):
            if trainer.is_global_zero:
                print(f"[immnet fit] stage {os.environ[resume.CHAIN_ENV]} has finished earlier ({ckpt_path.marker}): "
                      f"skipped, its best checkpoint is {ckpt_path.best}", file=sys.stderr, flush=True)
                _report(report, ckpt_path.best)
            return
        try:
            trainer.fit(model, ckpt_path=ckpt_path, **kwargs)
        except SIGTERMException:
            if trainer.is_global_zero:
                last = [Path(c.dirpath) / resume.LAST for c in trainer.checkpoint_callbacks
                        if isinstance(c, LastCheckpoint) and c.dirpath and (Path(c.dirpath) / resume.LAST).is_file()]
                print(f"[immnet fit] stopped by SIGTERM at step {trainer.global_step}; its last checkpoint is "
                      f"{last[0] if last else 'not written'} (resume: the same command with --ckpt_path last)",
                      file=sys.stderr, flush=True)
            raise SystemExit(128 + signal.SIGTERM) from None
        try:
            resume.mark_finished(trainer)
        except resume.StoppedShort as short:
            if trainer.is_global_zero:
                print(f"[immnet fit] {short}", file=sys.stderr, flush=True)
            raise SystemExit(resume.STOPPED_SHORT) from None
        if trainer.is_global_zero:
            _report(report, resume.best_checkpoint(trainer))


def _report(fd: str | None, best: str) -> None:
    """Hand a chained stage's best checkpoint to the chain (through the pipe ``fd`` that ``run_stages`` opened)."""
    import stat

    if fd:
        try:
            if stat.S_ISFIFO(os.fstat(int(fd)).st_mode):
                os.write(int(fd), (best or "").encode())
                os.close(int(fd))
        except OSError:  # not a pipe this process holds
            pass


def _configs(argv: list[str]):
    """Each ``--config`` of ``argv`` as ``(index, width, value)``: ``--config VALUE`` (width 2) or ``--config=VALUE``
    (width 1)."""
    for i, a in enumerate(argv):
        if a == "--config" and i + 1 < len(argv):
            yield i, 2, argv[i + 1]
        elif a.startswith("--config="):
            yield i, 1, a.split("=", 1)[1]


def _found(value: str) -> str:
    try:
        return str(resolve_path(value))
    except (OSError, ValueError):  # a YAML string, or a missing file for Lightning's CLI to report
        return value


def resolve_configs(argv: list[str]) -> list[str]:
    """``argv`` with each ``--config`` file found as ``immnet.config.resolve_path`` finds a path (as
    given, among the packaged configs, in the checkout; docs/configs.md), so that a packaged ablation
    (``--config configs/ablations/no-guard.yaml``) runs from any directory."""
    out = list(argv)
    for i, width, value in _configs(argv):
        out[i + width - 1] = _found(value) if width == 2 else "--config=" + _found(value)
    return out


def stage_entry(stage, i: int) -> tuple[list, str]:
    """A chain's ``i``-th entry (0-based) as ``(configs, checkpoint_as)``: ``configs`` the paths or inline
    configs given to the stage in order (each a ``--config``: a later one merges into the earlier), and
    ``checkpoint_as`` the argument that receives the previous stage's checkpoint."""
    arg = "stage1_checkpoint"
    if isinstance(stage, dict) and "config" in stage:  # {config: PATH or [PATH or INLINE, ...], checkpoint_as: ARG}
        configs = stage["config"] if isinstance(stage["config"], list) else [stage["config"]]
        if set(stage) - {"config", "checkpoint_as"} or not configs or not all(isinstance(c, (str, dict)) for c in configs):
            raise ValueError(f"stage {i + 1}: a stage with `config:` takes `config` (a path, or a list of paths and "
                             f"inline configs) and `checkpoint_as`, got {sorted(stage)}")
        arg = stage.get("checkpoint_as", arg)
        if arg not in ("stage1_checkpoint", "init_checkpoint"):
            raise ValueError(f"stage {i + 1}: checkpoint_as must be stage1_checkpoint or init_checkpoint, got {arg!r}")
        return configs, arg
    return [stage], arg


def config_args(configs: list) -> list[str]:
    """``--config`` arguments of a stage's configs in order: paths resolved (``immnet.config.resolve_path``),
    inline configs as YAML text."""
    out = []
    for config in configs:
        out += ["--config", str(resolve_path(config)) if isinstance(config, str) else yaml.safe_dump(config)]
    return out


def _die_with_parent(parent: int) -> None:
    """In a stage's process, before it runs: SIGTERM when the chain's process dies (Linux)."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
        if os.getppid() != parent:  # the chain died before the line above
            os.kill(os.getpid(), signal.SIGTERM)


def _run_stage(cmd: list[str], env: dict) -> tuple[int, str, int | None]:
    """Run one stage's process; ``(exit code, best checkpoint it reported, signal the chain got)``.
    SIGTERM or SIGINT sent to the chain meanwhile is passed on to the stage as SIGTERM."""
    read, write = os.pipe()
    parent, got = os.getpid(), []
    proc = subprocess.Popen(cmd, env={**env, _RESULT_ENV: str(write)}, pass_fds=(write,),
                            preexec_fn=lambda: _die_with_parent(parent))
    os.close(write)

    def forward(signum, frame):
        got.append(signum)
        proc.send_signal(signal.SIGTERM)

    old = {s: signal.signal(s, forward) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        code = proc.wait()
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    os.set_blocking(read, False)  # the stage has written and closed its end, or never will
    try:
        best = os.read(read, 1 << 16).decode().strip()
    except BlockingIOError:
        best = ""
    finally:
        os.close(read)
    return code, best, (got[0] if got else None)


def run_stages(recipe: dict, extra: list[str], label: str | None = None) -> str:
    """Run a chained recipe, each stage in its own process; returns the last run's best checkpoint.

    A rerun skips the stages that have finished (each says so) and resumes the unfinished one from
    its last checkpoint (:func:`immnet.training.resume.plan`). Each stage's W&B run is named
    ``"<label> <i>/<n>"`` (``"<label>"`` for a chain of one) through wandb's ``WANDB_NAME`` (``label``:
    ``WANDB_NAME`` if set, else the recipe's file name), unless the stage's logger names it; the group
    and job type come from wandb's own ``WANDB_RUN_GROUP`` and ``WANDB_JOB_TYPE``."""
    from immnet.training.resume import CHAIN_ENV, STOPPED_SHORT

    ckpt = None
    n = len(recipe["stages"])
    for i, stage in enumerate(recipe["stages"]):
        configs, arg = stage_entry(stage, i)
        cmd = [sys.executable, "-m", "immnet.cli", "fit", *config_args(configs), *extra]
        name = " + ".join(c if isinstance(c, str) else "an inline config" for c in configs)
        if ckpt is not None:
            cmd += [f"--model.init_args.{arg}", ckpt]
        print(f"[immnet fit] stage {i + 1}/{n}: {name}", file=sys.stderr, flush=True)
        base = os.environ.get("WANDB_NAME") or label
        run_name = {"WANDB_NAME": f"{base} {i + 1}/{n}" if n > 1 else base} if base else {}
        code, ckpt, signum = _run_stage(cmd, {**os.environ, CHAIN_ENV: f"{i + 1}/{n}", **run_name})
        if signum is not None:
            print(f"[immnet fit] stopped by signal {signum} in stage {i + 1}/{n} ({name}); the same command "
                  "resumes it", file=sys.stderr, flush=True)
            raise SystemExit(128 + signum)
        if code == STOPPED_SHORT:
            print(f"[immnet fit] stage {i + 1}/{n} ({name}) stopped short of its budget (above): the chain stops "
                  "here, and the same command resumes that stage", file=sys.stderr, flush=True)
            raise SystemExit(STOPPED_SHORT)
        if code != 0:
            raise SystemExit(f"[immnet fit] stage {i + 1}/{n} ({name}) failed with exit code {code}")
        if not ckpt:
            raise RuntimeError(f"stage {i + 1} left no checkpoint (is a ModelCheckpoint configured?)")
        print(f"[immnet fit] stage {i + 1} checkpoint: {ckpt}", file=sys.stderr, flush=True)
    return ckpt


def _run(argv: list[str]) -> IMMNetCLI:
    """One Lightning run; ``sys.argv`` becomes its command line (what a DDP launcher re-runs)."""
    from immnet.data.datamodule import LASTDataModule

    os.environ.setdefault("WANDB_SILENT", "true")
    saved, sys.argv = sys.argv, [sys.argv[0], *argv]
    try:
        return IMMNetCLI(
            L.LightningModule,
            LASTDataModule,
            subclass_mode_model=True,
            args=argv,
            save_config_kwargs={"overwrite": True},
            auto_configure_optimizers=False,
        )
    finally:
        sys.argv = saved


def lightning_main(argv: list[str]) -> int:
    """Run Lightning's CLI; a first ``--config`` holding ``stages:`` runs the chain, and every
    further argument (another ``--config`` too, e.g. an ablation) applies to each stage."""
    argv = resolve_configs(argv)
    i, width, config = next(_configs(argv), (None, 0, None))
    if argv[0] == "fit" and config is not None:
        try:
            recipe = yaml.safe_load(resolve_path(config).read_text())
        except OSError:  # no such file: a YAML string (an inline stage), or an error for Lightning's CLI to report
            recipe = None
        if isinstance(recipe, dict) and "stages" in recipe:
            run_stages(recipe, argv[1:i] + argv[i + width :], label=Path(config).stem)
            return 0
    _run(argv)
    return 0
