"""Callbacks of every training run: plain-text progress (one line per validation, readable in logs and
CI; under DDP only rank 0 prints, its validation metrics averaged over the ranks) and the last
checkpoint a run resumes from."""

from __future__ import annotations

import sys
import time

import lightning as L
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.utilities.exceptions import SIGTERMException


class PrintProgress(L.Callback):
    """Print step, elapsed time, the training loss and the validation metrics after each validation."""

    def __init__(self, every_n_steps: int = 0):
        self.every = every_n_steps
        self.start = None

    def on_train_start(self, trainer, pl_module):
        if not trainer.is_global_zero:
            return
        self.start = time.time()
        n = sum(p.numel() for p in pl_module.parameters())
        learn = sum(p.numel() for p in pl_module.parameters() if p.requires_grad)
        frozen = "" if learn == n else f" ({learn:,} learn, the rest frozen)"
        print(f"[train] {type(pl_module).__name__}: {n:,} parameters{frozen}", file=sys.stderr, flush=True)

    def _line(self, trainer, prefix):
        m = trainer.callback_metrics
        shown = " ".join(f"{k}={float(v):.4g}" for k, v in sorted(m.items()) if k.startswith(prefix))
        return f"[train] epoch {trainer.current_epoch} batch {trainer.global_step} {time.time() - self.start:6.0f}s {shown}"

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if self.start is not None and self.every and trainer.global_step % self.every == 0:
            print(self._line(trainer, "train/"), file=sys.stderr, flush=True)

    def on_validation_end(self, trainer, pl_module):
        if self.start is not None and not trainer.sanity_checking:
            print(self._line(trainer, ""), file=sys.stderr, flush=True)


class LastCheckpoint(ModelCheckpoint):
    """``last.ckpt`` beside the run's best checkpoint, the state ``immnet fit --ckpt_path last`` resumes.

    Written at every validation (after the best checkpoint's callback, so that it holds the best
    score of that validation too), when training ends, and when the run stops on SIGTERM: Lightning
    then finishes the running batch and raises ``SIGTERMException``, and this callback saves that
    batch's state. An interrupt (SIGINT) can stop the run inside a batch, so it writes nothing and the
    last validation's ``last.ckpt`` stays. Each save is atomic (Lightning writes a temporary file and
    renames it), so a ``kill -9`` leaves the previous ``last.ckpt`` whole. ``dirpath`` defaults to the
    directory of the run's first other ``ModelCheckpoint`` (its best checkpoint).

    ``immnet fit`` adds it to every run (``last_checkpoint:`` in a config sets its ``dirpath``).
    """

    def __init__(self, dirpath: str | None = None):
        super().__init__(dirpath=dirpath, filename=self.CHECKPOINT_NAME_LAST, monitor=None, save_top_k=1,
                         save_on_exception=True, enable_version_counter=False)

    def setup(self, trainer, pl_module, stage):
        if self.dirpath is None:
            best = [c for c in trainer.checkpoint_callbacks if isinstance(c, ModelCheckpoint) and c is not self]
            if best and best[0].dirpath:
                self.dirpath = best[0].dirpath
        super().setup(trainer, pl_module, stage)

    def on_exception(self, trainer, pl_module, exception):
        if isinstance(exception, SIGTERMException):  # raised between batches: a consistent state
            super().on_exception(trainer, pl_module, exception)

    def on_train_end(self, trainer, pl_module):
        if self._last_global_step_saved != trainer.global_step and not trainer.sanity_checking:
            self._save_none_monitor_checkpoint(trainer, self._monitor_candidates(trainer))
