"""What ``immnet fit`` does with what it finds in its checkpoint directory (docs/immnet.md, "Training").

A run's checkpoint directory (the ``dirpath`` of its ``ModelCheckpoint``) holds ``best.ckpt`` (the best
validation loss), ``last.ckpt`` (:class:`immnet.training.callbacks.LastCheckpoint`: every validation,
the end, SIGTERM) and, once training has ended normally, ``finished.json`` (the best checkpoint's path
and the final step). A run has ended normally when it reached its budget (``max_steps``, else ``max_epochs``)
or an ``EarlyStopping`` callback stopped it; a run stopped short of its budget otherwise (by ``max_time``, or
any callback that stops the trainer) is not finished: :func:`mark_finished` refuses it
(:class:`StoppedShort`), ``immnet fit`` says so and exits with :data:`STOPPED_SHORT`, and its
``last.ckpt`` is what a rerun resumes. Before training:

- ``--ckpt_path last`` resumes from ``last.ckpt``; without one it is an error (nothing to resume).
- A fresh run (no ``--ckpt_path``) into a directory that holds any of these files is refused, so that a
  rerun never overwrites an earlier run's best checkpoint silently; ``--overwrite_checkpoints true``
  starts afresh over it (removing the old ``last.ckpt`` and ``finished.json`` at once, ``best.ckpt``
  at the first validation).
- A stage of a chained recipe (``IMMNET_CHAIN_STAGE`` set by ``run_stages``) is skipped when its
  directory holds ``finished.json``, resumes from ``last.ckpt`` when there is one, and else starts
  afresh under the rule above.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from lightning.pytorch.callbacks import ModelCheckpoint

from immnet.data.scratch import publishing
from immnet.training.callbacks import LastCheckpoint, budget

FINISHED = "finished.json"
LAST = "last.ckpt"
CHAIN_ENV = "IMMNET_CHAIN_STAGE"
"""Set by ``run_stages`` to ``I/N`` for the ``immnet fit`` of stage ``I`` of ``N``."""
STOPPED_SHORT = 3
"""The exit code of an ``immnet fit`` whose training stopped short of its budget (not finished)."""


class StoppedShort(RuntimeError):
    """A run's training stopped short of its budget: it is not finished (the message says where and why)."""


class Finished:
    """A chained stage whose run has ended earlier: ``best`` is its best checkpoint."""

    def __init__(self, marker: Path):
        self.marker = marker
        self.best = json.loads(marker.read_text()).get("best", "")


def checkpoint_dirs(trainer) -> list[Path]:
    """The directories the run's checkpoint callbacks write to, where known before training: their
    ``dirpath``, or ``default_root_dir/checkpoints`` without a logger (a logger's versioned
    directory is new for each run)."""
    dirs = []
    for cb in trainer.checkpoint_callbacks:
        if isinstance(cb, LastCheckpoint) or not isinstance(cb, ModelCheckpoint):
            continue
        if cb.dirpath is not None:
            dirs.append(Path(cb.dirpath))
        elif not trainer.loggers:
            dirs.append(Path(trainer.default_root_dir) / "checkpoints")
    return list(dict.fromkeys(dirs))


def _held(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if p.suffix == ".ckpt" or p.name == FINISHED) if d.is_dir() else []


def plan(trainer, ckpt_path: str | None, overwrite: bool = False) -> str | None | Finished:
    """The ``ckpt_path`` to hand to ``trainer.fit``, or :class:`Finished` for a chained stage to skip;
    raises ``FileNotFoundError`` / ``FileExistsError`` as the module doc says."""
    dirs = checkpoint_dirs(trainer)
    stage = os.environ.get(CHAIN_ENV)
    if stage and ckpt_path is None and not overwrite:
        done = [d / FINISHED for d in dirs if (d / FINISHED).is_file()]
        if done:
            return Finished(done[0])
        if any((d / LAST).is_file() for d in dirs):
            ckpt_path = "last"
    if ckpt_path == "last":
        last = [d / LAST for d in dirs if (d / LAST).is_file()]
        if not last:
            where = ", ".join(map(str, dirs)) or "(no checkpoint directory is configured)"
            raise FileNotFoundError(f"--ckpt_path last: there is no last checkpoint ({LAST}) in {where}, so nothing "
                                    "to resume; run without --ckpt_path to start afresh")
        if trainer.is_global_zero:
            print(f"[immnet fit] resuming from {last[0]}", file=sys.stderr, flush=True)
        return "last"
    if ckpt_path is None:
        for d in dirs:
            held = _held(d)
            if held and not overwrite:
                raise FileExistsError(f"{d} holds {', '.join(held)} of an earlier run: resume it with --ckpt_path last, "
                                      "or start afresh over it with --overwrite_checkpoints true")
            if held and trainer.is_global_zero:
                for name in (LAST, FINISHED):
                    (d / name).unlink(missing_ok=True)
                print(f"[immnet fit] starting afresh over the earlier run in {d} (--overwrite_checkpoints)",
                      file=sys.stderr, flush=True)
    return ckpt_path


def best_checkpoint(trainer) -> str:
    """The run's best checkpoint (its first checkpoint callback's), else its last; "" without either."""
    cb = trainer.checkpoint_callback
    return (cb.best_model_path or cb.last_model_path) if cb is not None else ""


def stopped_short(trainer) -> str | None:
    """Why the run's training ended before its budget (``max_steps`` or ``max_epochs``), or ``None`` when it
    reached it or an ``EarlyStopping`` callback stopped it (a stop the config asked for)."""
    from lightning.pytorch.callbacks import EarlyStopping, Timer
    from lightning.pytorch.callbacks.early_stopping import EarlyStoppingReason

    loop = trainer.fit_loop
    if trainer.max_steps is not None and 0 <= trainer.max_steps <= trainer.global_step:
        return None
    if loop.max_epochs is not None and 0 <= loop.max_epochs <= loop.epoch_progress.current.processed:
        return None
    if any(isinstance(c, EarlyStopping) and c.stopping_reason != EarlyStoppingReason.NOT_STOPPED for c in trainer.callbacks):
        return None
    timers = [c for c in trainer.callbacks if isinstance(c, Timer) and c._duration is not None]
    if timers and (timers[0].time_remaining("train") or 0.0) <= 0.0:
        t = int(timers[0]._duration)
        return (f"its time limit max_time ({t // 86400:02d}:{t % 86400 // 3600:02d}:{t % 3600 // 60:02d}:{t % 60:02d}) "
                "ran out")
    if trainer.should_stop:
        return "a callback stopped the trainer"
    return "the trainer ended with no training batch left to run"


def mark_finished(trainer) -> None:
    """Write ``finished.json`` in each checkpoint directory of a run whose training ended normally (its
    budget reached, or stopped early by ``EarlyStopping``); raise :class:`StoppedShort` for a run stopped
    short of its budget, which is not finished and writes nothing."""
    if trainer.interrupted:
        return
    why = stopped_short(trainer)
    if why is not None:
        n = budget(trainer)
        alone = "--ckpt_path last" + (" and a larger --trainer.max_time or none, as the time spent counts against it"
                                      if "max_time" in why else "")
        raise StoppedShort(
            f"training stopped at step {trainer.global_step} of {n} ({why}), short of its budget: the run is not "
            f"finished (no {FINISHED} is written), its best checkpoint so far ({best_checkpoint(trainer) or 'none'}) "
            f"is not the config's model, and the same command resumes it from {LAST} (a single run: with {alone})")
    if not trainer.is_global_zero:
        return
    record = {"best": best_checkpoint(trainer), "global_step": int(trainer.global_step)}
    for d in checkpoint_dirs(trainer):
        d.mkdir(parents=True, exist_ok=True)
        with publishing(d / FINISHED) as tmp:
            tmp.write_text(json.dumps(record, indent=1) + "\n")
