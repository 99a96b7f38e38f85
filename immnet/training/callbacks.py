"""Callbacks of every training run: plain-text progress (readable in logs and CI; under DDP only rank 0
prints, its validation metrics averaged over the ranks) and the last checkpoint a run resumes from."""

from __future__ import annotations

import sys
import time

import lightning as L
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.utilities.exceptions import SIGTERMException

from immnet.progress import duration


class PrintProgress(L.Callback):
    """Progress lines on stderr: one after each validation (the training loss and the validation
    metrics), and between validations one every ``every_n_steps`` optimizer steps (0: none) and one
    whenever ``every_seconds`` have passed since the last line, so that a slow run (a busy machine)
    still says where it is at least that often. Each line reads
    ``[train] step K/N epoch E elapsed 2m05s left ~6m40s <metrics>``: N is the run's step budget
    (``max_steps``, else ``max_epochs`` passes), elapsed counts from the start of this process's training,
    and the time left is the mean time per step so far (this process's steps: a resumed run counts from
    its resumed step) times the steps to go."""

    clock = staticmethod(time.monotonic)
    """The clock the lines read (seconds; a test replaces it on the instance)."""

    def __init__(self, every_n_steps: int = 0, every_seconds: float = 60.0):
        self.every = every_n_steps
        self.every_seconds = every_seconds
        self.start = None
        self.first_step = 0
        self.last_line = None

    def on_train_start(self, trainer, pl_module):
        if not trainer.is_global_zero:
            return
        self.start = self.last_line = self.clock()
        self.first_step = trainer.global_step
        n = sum(p.numel() for p in pl_module.parameters())
        learn = sum(p.numel() for p in pl_module.parameters() if p.requires_grad)
        frozen = "" if learn == n else f" ({learn:,} learn, the rest frozen)"
        print(f"[train] {type(pl_module).__name__}: {n:,} parameters{frozen}", file=sys.stderr, flush=True)

    def _line(self, trainer, prefix):
        from immnet.training.resume import budget

        now = self.clock()
        k, n = trainer.global_step, budget(trainer)
        done = k - self.first_step
        left = f"~{duration((now - self.start) / done * max(n - k, 0))}" if done > 0 else "?"
        m = trainer.callback_metrics
        shown = " ".join(f"{key}={float(v):.4g}" for key, v in sorted(m.items()) if key.startswith(prefix))
        self.last_line = now
        return (f"[train] step {k}/{n} epoch {trainer.current_epoch} elapsed {duration(now - self.start)} "
                f"left {left} {shown}").rstrip()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if self.start is None:
            return
        by_steps = self.every and trainer.global_step % self.every == 0
        by_time = self.every_seconds and self.clock() - self.last_line >= self.every_seconds
        if by_steps or by_time:
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
