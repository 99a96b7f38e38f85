"""Plain-text progress for training: one line per validation, readable in logs and CI (no TTY needed).
Under DDP only rank 0 prints (its validation metrics are averaged over the ranks)."""

from __future__ import annotations

import sys
import time

import lightning as L


class PrintProgress(L.Callback):
    """Print step, elapsed time, the training loss and the validation metrics after each validation."""

    def __init__(self, every_n_steps: int = 0):
        self.every = every_n_steps
        self.start = None

    def on_train_start(self, trainer, pl_module):
        if not trainer.is_global_zero:
            return
        self.start = time.time()
        print(f"[train] {type(pl_module).__name__}: {sum(p.numel() for p in pl_module.parameters()):,} parameters", file=sys.stderr, flush=True)

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
