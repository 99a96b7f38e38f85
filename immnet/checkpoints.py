"""Checkpoint files read without running anything from them, and a checksum of the weights they hold.

    ckpt = load_checkpoint("runs/quick/stage2/checkpoints/best.ckpt")   # a dict; CheckpointError if refused
    add_checksum(ckpt)                                                 # before torch.save of a checkpoint

``load_checkpoint`` is the one reader of checkpoint files in the package (the tracker, Stage2Module's
``stage1_checkpoint`` / ``init_checkpoint``, the exporter, and Lightning's resume through
``immnet.training.checkpoint_io.SafeCheckpointIO``). It unpickles with ``torch.load(weights_only=True)``:
tensors, dicts, lists, tuples, strings and numbers, plus ``ALLOWED_GLOBALS``; any other global in the
pickle (a function to call, a class to build) refuses the file before anything in it runs.

The checksum (``CHECKSUM_KEY``, docs/checkpoints.md) is a SHA-256 over the ``state_dict``: for each entry
in sorted name order, the UTF-8 JSON line ``["name", "torch.float32", [shape...]]\\n`` then the tensor's
bytes (C order, little-endian). A file whose weights disagree with its stored checksum is refused; a
file without one (written before checkpoints carried it) is accepted, read as safely as any other.
"""

from __future__ import annotations

import hashlib
import json
import pickle
import re
import warnings
from pathlib import Path

CHECKSUM_KEY = "weights_sha256"
PRETRAINED = Path(__file__).resolve().parent / "pretrained" / "immnet.ckpt"
"""The shipped 3D-LAST weights (``immnet/pretrained/PROVENANCE.md``), the benchmark model; the others beside them."""
WEIGHTS_TABLE = PRETRAINED.with_name("weights.json")
"""The one table of shipped weights (docs/checkpoints.md "Shipped weights"): for each network its name, file,
weights checksum (checked at every load of the file: ``load_checkpoint``), the scan intervals it serves, the data it
was trained on, whether it keeps a range guard, a one-line summary and its provenance files; and the bank, the shipped
networks as one tracker (``immnet.tracking.bank``), the default of ``Tracker.pretrained()`` and ``immnet track``: its
members and how it weighs and runs them."""
TABLE = json.loads(WEIGHTS_TABLE.read_text())
WEIGHTS = {entry["name"]: entry for entry in TABLE["weights"]}
"""The table's networks by name."""
SHIPPED = {name: entry["file"] for name, entry in WEIGHTS.items()}
"""The shipped networks' files by name (read from ``WEIGHTS_TABLE``)."""
GENERAL = "general"
"""The general network: the bank's member for any interval from 0.5 to 12 s."""
BANK = TABLE["bank"]["name"]
"""The shipped networks together as one tracker (the table's ``bank``), not a file of its own."""
BANK_MEMBERS = tuple(TABLE["bank"]["members"])
"""The bank's networks by shipped name (``immnet.tracking.bank.DEFAULT_MEMBERS``)."""
BANK_SETTINGS = {k: TABLE["bank"][k] for k in ("likelihood", "temper", "prune", "prune_after", "defer")}
"""How the shipped bank weighs and runs its members (``immnet.tracking.bank``: ``LIKELIHOOD``, ``TEMPER``, ``PRUNE``,
``PRUNE_AFTER``, ``DEFER``), chosen on the validation sets (docs/tracking.md "A bank of networks")."""
DEFAULT_WEIGHTS = TABLE["default"]


def shipped(name: str) -> Path:
    """The file of the shipped network ``name`` (``SHIPPED``); a ValueError naming the choices otherwise."""
    if name not in SHIPPED:
        raise ValueError(f"no shipped weights named {name!r}; shipped: {', '.join(SHIPPED)}"
                         f"{' (and ' + BANK + ', all of them as one tracker: Tracker.pretrained)' if name == BANK else ''}")
    return PRETRAINED.with_name(SHIPPED[name])


def shipped_entry(path) -> dict | None:
    """The table's entry of a shipped file (a path inside ``immnet/pretrained`` named in the table), else None."""
    path = Path(path)
    if path.resolve().parent != PRETRAINED.parent:
        return None
    return next((entry for entry in TABLE["weights"] if entry["file"] == path.name), None)


def provenance_file(ckpt) -> Path:
    """Where shipped weights keep their provenance JSON (the table's ``provenance_json``, beside them); for a
    checkpoint of one's own ``provenance-STEM.json`` beside it (which need not exist)."""
    ckpt = Path(ckpt)
    entry = shipped_entry(ckpt)
    return ckpt.with_name(entry["provenance_json"] if entry else f"provenance-{ckpt.stem}.json")

ALLOWED_GLOBALS: tuple = ()
"""Globals a checkpoint of ours may hold beyond torch's weights-only set (tensors, storages, dtypes,
``OrderedDict``, ``torch.Size``, plain Python containers and scalars). Our Lightning checkpoints of
``Stage1Module`` / ``Stage2Module`` (state_dict, hyper_parameters from LightningCLI's YAML, loops,
ModelCheckpoint's and Timer's state, Adam's and LambdaLR's state) and the exported weights need none."""


ALLOWED_PACKAGES: tuple = ("immnet",)
"""The packages whose classes a checkpoint's config may name (every ``class_path`` in its ``hyper_parameters``):
a network is rebuilt from the classes its checkpoint names, and naming a class imports its module, so a file
naming another package's is refused before anything is imported. A network built of classes of one's own package
loads once that package is added (``immnet.checkpoints.ALLOWED_PACKAGES += ("mylab",)``; docs/checkpoints.md)."""

_HPARAMS = ("hyper_parameters", "datamodule_hyper_parameters")
"""Where a checkpoint keeps the configs it is rebuilt from (Lightning, and LightningCLI's ``--ckpt_path``)."""


class CheckpointError(ValueError):
    """A checkpoint file that is refused: unreadable, holding code, or with weights that fail its checksum."""


def weights_checksum(state_dict: dict) -> str:
    """SHA-256 (hex) of a ``state_dict``: names, dtypes, shapes and bytes, in sorted name order."""
    import torch

    digest = hashlib.sha256()
    for name in sorted(state_dict):
        t = state_dict[name]
        if not isinstance(t, torch.Tensor):
            raise ValueError(f"state_dict entry {name!r} is a {type(t).__name__}, not a tensor")
        t = t.detach().to("cpu").contiguous()
        digest.update((json.dumps([name, str(t.dtype), list(t.shape)]) + "\n").encode())
        digest.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def add_checksum(checkpoint: dict) -> dict:
    """Store the checksum of ``checkpoint["state_dict"]`` in ``checkpoint`` (in place); returns it."""
    checkpoint[CHECKSUM_KEY] = weights_checksum(checkpoint["state_dict"])
    return checkpoint


def verify_checksum(checkpoint: dict, name) -> None:
    """Refuse ``checkpoint`` (read from ``name``) if its weights disagree with its stored checksum;
    one without a checksum passes."""
    stored = checkpoint.get(CHECKSUM_KEY)
    if stored is None:
        return
    if not (isinstance(stored, str) and re.fullmatch(r"[0-9a-f]{64}", stored)):
        raise CheckpointError(f"{name}: its {CHECKSUM_KEY} is not a SHA-256 hex digest")
    if not isinstance(checkpoint.get("state_dict"), dict):
        raise CheckpointError(f"{name}: it carries a checksum but no state_dict")
    try:
        actual = weights_checksum(checkpoint["state_dict"])
    except ValueError as err:
        raise CheckpointError(f"{name}: {err}") from None
    if actual != stored:
        raise CheckpointError(f"{name}: its weights do not match the checksum stored in it "
                              f"(stored sha256 {stored[:16]}..., the weights give {actual[:16]}...): the file was altered or damaged")


def load_checkpoint(path: str | Path, map_location="cpu", check_table: bool = True) -> dict:
    """Read a checkpoint file as plain data (``weights_only=True`` with ``ALLOWED_GLOBALS``) and verify its
    checksum. ``FileNotFoundError`` for a missing file, ``CheckpointError`` (one line naming the file) for
    one that is unreadable, holds a global outside the allow-list, is not a dict, or fails its checksum, or a shipped
    file whose weights are not the ones the weights table names (``check_table``)."""
    import torch

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        with torch.serialization.safe_globals(list(ALLOWED_GLOBALS)), warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Detected pickle protocol")
            ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # a global off the allow-list; or a truncated, empty or foreign file
        found = isinstance(err, pickle.UnpicklingError) and re.search(r"GLOBAL ([\w.]+)", str(err))
        if found:
            raise CheckpointError(f"{path} is refused: it holds the global {found.group(1)}, which is not on "
                                  "the checkpoint allow-list (docs/checkpoints.md); nothing in it was run") from None
        raise CheckpointError(f"{path} is not a readable checkpoint: {_reason(err)}") from None
    if not isinstance(ckpt, dict):
        raise CheckpointError(f"{path} is not a checkpoint: it holds a {type(ckpt).__name__}, not a dict")
    foreign = foreign_classes([ckpt.get(k) for k in _HPARAMS])
    if foreign:
        raise CheckpointError(f"{path} is refused: its config names the class {foreign[0]!r}, outside the packages "
                              f"a checkpoint may build from ({', '.join(ALLOWED_PACKAGES)}; docs/checkpoints.md); "
                              "nothing in it was imported")
    verify_checksum(ckpt, path)
    if check_table:
        _check_table(ckpt, path)
    return ckpt


def _check_table(ckpt: dict, path: Path) -> None:
    """Refuse a shipped file (one the weights table names) whose weights are not the ones the table ships."""
    entry = shipped_entry(path)
    if entry is not None and ckpt.get(CHECKSUM_KEY) != entry["weights_sha256"]:
        raise CheckpointError(f"{path}: its weights are not the ones {WEIGHTS_TABLE.name} ships under "
                              f"{entry['name']!r} (sha256 {str(ckpt.get(CHECKSUM_KEY))[:16]}..., the table says "
                              f"{entry['weights_sha256'][:16]}...)")


def record_shipped(name: str) -> str:
    """Write the checksum of the file shipped as ``name`` (just exported: ``scripts/make_shipped.py``) into the weights
    table; returns it."""
    checksum = load_checkpoint(shipped(name), check_table=False)[CHECKSUM_KEY]
    text = WEIGHTS_TABLE.read_text()
    old = WEIGHTS[name]["weights_sha256"]
    WEIGHTS_TABLE.write_text(text.replace(f'"weights_sha256": "{old}"', f'"weights_sha256": "{checksum}"', 1))
    WEIGHTS[name]["weights_sha256"] = checksum
    return checksum


def foreign_classes(config) -> list:
    """The ``class_path`` (and LightningCLI's ``_class_path``) values anywhere in ``config`` (nested dicts and lists)
    that are not a dotted name inside one of ``ALLOWED_PACKAGES``, in the order found; nothing is imported."""
    found, stack = [], [config]
    while stack:
        node = stack.pop(0)
        if isinstance(node, dict):
            for key, value in node.items():
                if key in ("class_path", "_class_path") and not (
                        isinstance(value, str) and "." in value and value.split(".", 1)[0] in ALLOWED_PACKAGES):
                    found.append(value)
                stack.append(value)
        elif isinstance(node, (list, tuple)):
            stack.extend(node)
    return found


_BOILERPLATE = ("Weights only load failed", "Please file an issue", "Check the documentation")


def _reason(err: Exception) -> str:
    """The informative line of a ``torch.load`` error, first sentence only."""
    lines = [s.strip() for s in str(err).splitlines() if s.strip() and not s.strip().startswith(_BOILERPLATE)]
    if not lines:
        return "the file is empty or cut short" if isinstance(err, EOFError) else type(err).__name__
    end = re.search(r"\.\s+[A-Z]", lines[-1])
    return (lines[-1][: end.start()] if end else lines[-1]).rstrip(".")
