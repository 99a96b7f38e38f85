"""Progress lines of a training run (immnet/training/callbacks.PrintProgress) on a fake clock: a slow run
still prints where it is at least every minute, with its step, loss, elapsed time and time left."""

import re

import lightning as L
import torch
from lightning.pytorch.demos.boring_classes import BoringModel

from immnet.training.callbacks import PrintProgress, duration

SECONDS_PER_STEP = 25.0  # a run on a busy machine: one step every 25 s, validation never in 10 steps


class Timed(BoringModel):
    """A BoringModel whose every training step takes SECONDS_PER_STEP on the fake clock and logs
    train/loss = 0.5 * its step."""

    def __init__(self, clock):
        super().__init__()
        self.clock = clock

    def training_step(self, batch, batch_idx):
        self.clock[0] += SECONDS_PER_STEP
        out = super().training_step(batch, batch_idx)
        self.log("train/loss", 0.5 * (self.global_step + 1))
        return out


def test_a_progress_line_at_least_every_minute_with_step_loss_elapsed_and_time_left(capsys):
    """Issue 60, item 10: with no step cadence (every_n_steps 0, the recipes' setting) and no validation in
    sight, a line comes as soon as a minute has passed since the last one: after steps 3, 6 and 9 of 10
    at 25 s a step, each with step K/10, the loss the step logged, the elapsed time and the time left
    (elapsed / K * (10 - K)), computed here independently."""
    clock = [1000.0]
    progress = PrintProgress()
    progress.clock = lambda: clock[0]
    trainer = L.Trainer(max_steps=10, callbacks=[progress], logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0)
    trainer.fit(Timed(clock))
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("[train] step")]
    assert len(lines) == 3, lines
    for line, k in zip(lines, (3, 6, 9)):
        elapsed = SECONDS_PER_STEP * k
        left = elapsed / k * (10 - k)
        got = re.fullmatch(r"\[train\] step (\d+)/(\d+) epoch 0 elapsed (\S+) left ~(\S+) train/loss=(\S+)", line)
        assert got is not None, line
        assert (int(got[1]), int(got[2])) == (k, 10)
        assert got[3] == duration(elapsed) and got[4] == duration(left)
        assert float(got[5]) == 0.5 * k
    assert [duration(s) for s in (75, 175, 3725, 45)] == ["1m15s", "2m55s", "1h02m05s", "45s"]


def test_a_step_cadence_still_prints_on_its_steps(capsys):
    """every_n_steps keeps its cadence besides the minute (here a step takes no time on the clock)."""
    clock = [0.0]
    progress = PrintProgress(every_n_steps=4)
    progress.clock = lambda: clock[0]
    trainer = L.Trainer(max_steps=10, callbacks=[progress], logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0)
    trainer.fit(BoringModel())
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("[train] step")]
    assert [line.split()[2] for line in lines] == ["4/10", "8/10"]
    assert all("elapsed 0s left ~0s" in line for line in lines)
