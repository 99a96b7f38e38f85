"""Callbacks of every training run: plain-text progress (readable in logs and CI; under DDP only rank 0
prints, its validation metrics averaged over the ranks) and the last checkpoint a run resumes from."""

from __future__ import annotations

import sys
import threading
import time

import lightning as L
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.utilities.exceptions import SIGTERMException

from immnet.progress import duration


def budget(trainer) -> int:
    """The run's budget in optimizer steps: ``max_steps``, else ``max_epochs`` passes estimated by Lightning."""
    if trainer.max_steps is not None and trainer.max_steps >= 0:
        return int(trainer.max_steps)
    return int(trainer.estimated_stepping_batches)


class PrintProgress(L.Callback):
    """Progress lines on stderr: one after each validation (the training loss and the validation
    metrics), one every ``every_n_steps`` optimizer steps (0: none), and one whenever ``every_seconds``
    have passed since the last line, whatever the run is doing (a watch thread; a batch or a validation
    can take minutes on a busy machine), so that a slow run still says where it is at least that often.
    Each line reads ``[train] step K/N epoch E elapsed 2m05s left ~6m40s [(what it is doing)] <metrics>``:
    N is the run's step budget (``max_steps``, else ``max_epochs`` passes), elapsed counts from the start
    of this process's fit, and the time left is the mean time per step of this process's training so far
    (a resumed run counts from its resumed step) times the steps to go. Only rank 0 prints."""

    clock = staticmethod(time.monotonic)
    """The clock the lines read (seconds; a test replaces it on the instance)."""
    watch = True
    """Whether a thread prints the minute's line when no hook does (a test driving a fake clock turns it off)."""

    def __init__(self, every_n_steps: int = 0, every_seconds: float = 60.0):
        self.every = every_n_steps
        self.every_seconds = every_seconds
        self.start = self.train_start = self.last_line = None
        self.first_step = 0
        self.n = None  # the step budget
        self.metrics = {}  # the last metrics a hook saw: the watch thread reads these, never the trainer's
        self.doing = "starting"
        self._trainer = None
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread = None

    def on_fit_start(self, trainer, pl_module):
        if not trainer.is_global_zero:
            return
        self.start = self.last_line = self.clock()
        self._trainer = trainer
        self.n = trainer.max_steps if trainer.max_steps is not None and trainer.max_steps >= 0 else None  # else at the start of training
        n = sum(p.numel() for p in pl_module.parameters())
        learn = sum(p.numel() for p in pl_module.parameters() if p.requires_grad)
        frozen = "" if learn == n else f" ({learn:,} learn, the rest frozen)"
        self._say(f"[train] {type(pl_module).__name__}: {n:,} parameters{frozen}")
        if self.watch and self.every_seconds:
            self._stop.clear()
            self._thread = threading.Thread(target=self._watch, name="immnet-progress", daemon=True)
            self._thread.start()

    def _watch(self):
        while not self._stop.wait(min(1.0, self.every_seconds / 4)):
            self._tick(self._trainer, "train/", fresh=False)

    def _stop_watch(self):
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        self._thread = None

    def on_fit_end(self, trainer, pl_module):
        self._stop_watch()

    def on_exception(self, trainer, pl_module, exception):
        self._stop_watch()

    def teardown(self, trainer, pl_module, stage):
        self._stop_watch()

    def on_sanity_check_start(self, trainer, pl_module):
        if self.start is not None:
            self.doing = "checking validation before training"
            self._say(f"[train] {self.doing} (Lightning's sanity check)")

    def on_train_start(self, trainer, pl_module):
        self.n = budget(trainer)
        self.train_start, self.first_step, self.doing = self.clock(), trainer.global_step, "training"

    def on_validation_start(self, trainer, pl_module):
        if not trainer.sanity_checking:
            self.doing = "validating"

    def _say(self, line):
        with self._lock:
            self.last_line = self.clock()
            print(line, file=sys.stderr, flush=True)

    def _line(self, trainer, prefix, fresh=True):
        """The progress line; ``fresh``: read the trainer's metrics (the training thread only), else the last seen."""
        if fresh:
            self.metrics = {key: float(v) for key, v in trainer.callback_metrics.items()}
        now = self.clock()
        k, n = trainer.global_step, "?" if self.n is None else self.n
        done = k - self.first_step
        left = f"~{duration((now - self.train_start) / done * max(n - k, 0))}" if done > 0 and self.train_start is not None else "?"
        doing = "" if self.doing == "training" else f" ({self.doing})"
        shown = " ".join(f"{key}={v:.4g}" for key, v in sorted(self.metrics.items()) if key.startswith(prefix))
        return (f"[train] step {k}/{n} epoch {trainer.current_epoch} elapsed {duration(now - self.start)} "
                f"left {left}{doing} {shown}").rstrip()

    def _tick(self, trainer, prefix, fresh=True):
        """The minute's line, if a minute has passed since the last line."""
        with self._lock:
            if self.start is not None and self.every_seconds and self.clock() - self.last_line >= self.every_seconds:
                self._say(self._line(trainer, prefix, fresh))

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if self.start is None:
            return
        if self.every and trainer.global_step % self.every == 0:
            self._say(self._line(trainer, "train/"))
        else:
            self._tick(trainer, "train/")

    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0):
        self._tick(trainer, "train/")

    def on_validation_end(self, trainer, pl_module):
        if self.start is not None and not trainer.sanity_checking:
            self.doing = "training"
            self._say(self._line(trainer, ""))


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
