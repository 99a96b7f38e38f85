"""3D-LAST: the generator, data sets on disk, the Lightning DataModule and a TorchRL environment.

``generate`` makes trajectories in memory, ``write_dataset`` / ``load_dataset`` / ``export_npz``
handle data sets on disk (memmapped directory or ``.npz``), ``LASTDataModule`` batches them for
training and ``LASTEnv`` streams them to a tracker policy. ``immnet.data.real.make_adsb`` makes data sets of
real ADS-B flights seen by a simulated radar. See ``docs/data.md``.

The names below load their modules (torch, Lightning, TorchRL) when first asked for, so that importing a light
submodule (``immnet.data.cli`` to build ``immnet --help``, ``immnet.data.spec``) loads none of them.
"""

import sys
import types

from immnet.lazy import lazy_names

__getattr__, __dir__, __all__ = lazy_names(__name__, {
    "BLOCK": "immnet.data.generate", "generate": "immnet.data.generate", "SPEC_VERSION": "immnet.data.spec",
    "DataSpec": "immnet.data.spec", "as_batch": "immnet.data.storage", "export_npz": "immnet.data.storage",
    "load_dataset": "immnet.data.storage", "write_dataset": "immnet.data.storage",
    "LASTDataModule": "immnet.data.datamodule", "LASTEnv": "immnet.data.env",
})


class _Package(types.ModuleType):
    """``immnet.data.generate`` is the function, as ``from immnet.data import generate`` reads it: the import system
    binds a package's attribute to each submodule it loads, which here would shadow the function by its module
    ``immnet.data.generate`` (still in ``sys.modules`` and importable by name)."""

    def __setattr__(self, name, value):
        if name == "generate" and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
