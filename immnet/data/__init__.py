"""3D-LAST: the generator, data sets on disk, the Lightning DataModule and a TorchRL environment.

``generate`` makes trajectories in memory, ``write_dataset`` / ``load_dataset`` / ``export_npz``
handle data sets on disk (memmapped directory or ``.npz``), ``LASTDataModule`` batches them for
training and ``LASTEnv`` streams them to a tracker policy. ``immnet.data.real.make_adsb`` makes data sets of
real ADS-B flights seen by a simulated radar. See ``docs/data.md``.
"""

from immnet.data.generate import BLOCK, generate
from immnet.data.spec import SPEC_VERSION, DataSpec
from immnet.data.storage import as_batch, export_npz, load_dataset, write_dataset

__all__ = [
    "BLOCK", "SPEC_VERSION", "DataSpec", "LASTDataModule", "LASTEnv", "as_batch", "export_npz",
    "generate", "load_dataset", "write_dataset",
]


def __getattr__(name):  # Lightning and TorchRL load only when asked for
    if name == "LASTDataModule":
        from immnet.data.datamodule import LASTDataModule

        return LASTDataModule
    if name == "LASTEnv":
        from immnet.data.env import LASTEnv

        return LASTEnv
    raise AttributeError(f"module 'immnet.data' has no attribute {name!r}")
