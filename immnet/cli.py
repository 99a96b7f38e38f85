"""The ``immnet`` command.

``immnet fit|validate|test ...`` go to Lightning's CLI (see ``immnet.training.cli``); every other
subcommand is a plain argparse command registered by its package (``register(subparsers)``).
"""

from __future__ import annotations

import argparse
import importlib
import sys

# Each module exposes ``register(subparsers)``; a missing one is skipped so the CLI grows by file.
_COMMAND_MODULES = (
    "immnet.data.cli",
    "immnet.evaluation.cli",
    "immnet.evaluation.tune_cli",
    "immnet.tracking.cli",
)
_LIGHTNING_COMMANDS = ("fit", "validate", "test")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="immnet", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in _COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as err:
            if err.name != name and not name.startswith(f"{err.name}."):
                raise
            continue
        module.register(sub)
    for name in _LIGHTNING_COMMANDS:
        sub.add_parser(name, help=f"Lightning CLI: {name} a recipe (immnet {name} --help)", add_help=False)
    return parser


def main(argv: list[str] | None = None) -> int:
    from immnet.data.scratch import Terminated

    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in _LIGHTNING_COMMANDS:
        from immnet.checkpoints import CheckpointError
        from immnet.training.cli import lightning_main

        try:
            return lightning_main(argv)
        except (CheckpointError, FileNotFoundError, FileExistsError) as err:
            # a refused --ckpt_path / stage1_checkpoint / init_checkpoint, or what a run finds in its
            # checkpoint directory
            print(f"immnet {argv[0]}: error: {err}", file=sys.stderr)
            return 2
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, OSError) as err:  # OSError: a full disk, a read-only folder, a missing file, ...
        print(f"immnet {args.command}: error: {_reason(err)}", file=sys.stderr)
        return 2
    except Terminated:
        print(f"immnet {args.command}: terminated (SIGTERM); its temporary files are removed", file=sys.stderr)
        return 128 + 15


def _reason(err: Exception) -> str:
    """One line: an ``OSError`` the system raised as ``PATH: reason`` (``strerror``: "No space left on device",
    "Permission denied", ...), any other error as its message."""
    if isinstance(err, OSError) and err.filename is not None and err.strerror:
        also = f" -> {err.filename2}" if err.filename2 is not None else ""
        return f"{err.filename}{also}: {err.strerror}"
    return str(err)


if __name__ == "__main__":
    sys.exit(main())
