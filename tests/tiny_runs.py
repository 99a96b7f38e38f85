"""Tiny real runs shared by the test modules (a module of helpers, not a test file)."""

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
