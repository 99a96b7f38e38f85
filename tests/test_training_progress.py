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
    progress.clock, progress.watch = (lambda: clock[0]), False  # the clock moves only in the steps
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
    progress.clock, progress.watch = (lambda: clock[0]), False
    trainer = L.Trainer(max_steps=10, callbacks=[progress], logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0)
    trainer.fit(BoringModel())
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("[train] step")]
    assert [line.split()[2] for line in lines] == ["4/10", "8/10"]
    assert all("elapsed 0s left ~0s" in line for line in lines), lines


class SlowValidation(BoringModel):
    """Each validation batch takes 40 s on the fake clock."""

    def __init__(self, clock):
        super().__init__()
        self.clock = clock

    def validation_step(self, batch, batch_idx):
        self.clock[0] += 40.0
        return super().validation_step(batch, batch_idx)


def test_the_check_before_training_says_so_and_a_long_one_still_prints_each_minute(capsys):
    """Issue 60, item 10: on a busy machine Lightning's validation check before training took 6 minutes in
    silence: it is announced, and its batches (40 s each on the fake clock) print the minute's line."""
    clock = [0.0]
    progress = PrintProgress()
    progress.clock, progress.watch = (lambda: clock[0]), False
    trainer = L.Trainer(max_steps=2, callbacks=[progress], logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=3,
                        limit_val_batches=3, val_check_interval=2)
    trainer.fit(SlowValidation(clock))
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("[train]")]
    assert lines[1] == "[train] checking validation before training (Lightning's sanity check)"
    assert lines[2] == "[train] step 0/2 epoch 0 elapsed 1m20s left ? (checking validation before training)"
    # the check's batches end at 40, 80 (a line: 80 s since the start), 120 s; the two steps take no time;
    # the validation at step 2: its first batch ends at 160 s, 80 s after the last line, and says so
    assert lines[3] == "[train] step 2/2 epoch 0 elapsed 2m40s left ~0s (validating)"


def test_a_step_that_takes_minutes_still_gets_its_line(capsys):
    """The watch thread prints while no hook runs (here one step of 1.5 s, the minute shrunk to 0.2 s),
    and is stopped when the fit ends."""
    import time

    class OneSlowStep(BoringModel):
        def training_step(self, batch, batch_idx):
            if self.global_step == 0:
                time.sleep(1.5)
            return super().training_step(batch, batch_idx)

    progress = PrintProgress(every_seconds=0.2)
    trainer = L.Trainer(max_steps=2, callbacks=[progress], logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0)
    trainer.fit(OneSlowStep())
    lines = capsys.readouterr().err.splitlines()
    assert any(line.startswith("[train] step 0/2 epoch 0 elapsed") for line in lines), lines
    assert progress._thread is None and not [t for t in __import__("threading").enumerate() if t.name == "immnet-progress"]
