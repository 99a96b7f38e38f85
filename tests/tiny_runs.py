"""Tiny real runs shared by the test modules (a module of helpers, not a test file)."""

import csv

import lightning as L
import torch

from immnet import keys
from immnet.data.spec import DataSpec
from immnet.data.storage import write_dataset

TINY = DataSpec(T=40, min_segment=12)
"""Trajectories short enough for a real ``immnet fit`` of the quick recipes in seconds."""


def write_quick_data(root, spec: DataSpec = TINY, test: bool = False):
    """``root/runs/quick/data`` as ``scripts/main.sh`` lays it out, tiny: a train set of 24, the four
    single-mode sets of 8 (stage 1) and, with ``test``, a test set of 6; returns ``root``."""
    data = root / "runs/quick/data"
    write_dataset(data / "train", 24, seed=11, spec=spec)
    for i, mode in enumerate(("cv", "ca", "ct+", "ct-")):
        write_dataset(data / f"single-{mode}", 8, seed=12 + i, spec=spec, single_mode=mode)
    if test:
        write_dataset(data / "test", 6, seed=99, spec=spec)
    return root


def at_an_interval_it_takes(method, batch):
    """``batch`` as ``method`` can take it: for a learned tracker trained over a range of scan intervals that leaves
    out the batch's (the shipped ``real-5s``: 4.5-5.5 s), every scan at the middle of that range (``dt``, no times);
    any other method gets ``batch`` as it is. A method told each detection's covariance (``keys.MEAS_COV`` in its
    ``needs``: ``r: detection``) gets ``r^2 I`` at each detection (``r`` the batch's per track, else 5 m; NaN where
    missed) where the batch has none. For the tests that run every registry method on 1 s data."""
    if keys.MEAS_COV in getattr(method, "needs", ()) and keys.MEAS_COV not in batch.keys():
        z = batch[keys.MEASUREMENTS]
        r = batch[keys.R].to(z.dtype) if keys.R in batch.keys() else torch.full(batch.batch_size, 5.0, dtype=z.dtype)
        cov = (r**2)[:, None, None, None] * torch.eye(3, dtype=z.dtype).expand(*z.shape[:2], 3, 3)
        cov = torch.where(torch.isnan(z).any(-1)[..., None, None], torch.full_like(cov, float("nan")), cov)
        batch = batch.clone()
        batch[keys.MEAS_COV] = cov
    span = getattr(getattr(method, "net", None), "interval_range", None)
    if span is None:
        return batch
    lo, hi = float(span[0]), float(span[1])
    dt = batch["dt"] if "dt" in batch.keys() else None
    if dt is not None and keys.TIME not in batch.keys() and bool(((dt >= lo) & (dt <= hi)).all()):
        return batch
    out = batch.clone()
    if keys.TIME in out.keys():
        del out[keys.TIME]
    out["dt"] = torch.full(out.batch_size, (lo + hi) / 2, dtype=torch.float64)
    return out



def write_csv(path, header, rows):
    """A CSV file at ``path``: ``header`` then ``rows`` (the tests' inputs of ``immnet track``); returns ``path``."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)
    return path


class StopAt(L.Callback):
    """Stops the trainer once it has made ``step`` optimizer steps, as a guard callback (``max_time``) would."""

    def __init__(self, step: int):
        self.step = step

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step >= self.step:
            trainer.should_stop = True
