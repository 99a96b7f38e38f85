"""Temporary siblings of outputs: how a writer makes, publishes and cleans them.

A writer of ``DIR/NAME`` works in the hidden sibling ``DIR/.NAME.tmp-PID-HEX`` (``PID`` its process
id) and renames it onto ``NAME`` only when complete (:func:`replace`, atomic on one file system),
so a reader never sees a partial output.

:func:`publishing` is that whole protocol around one writer's work. Leftovers: a writer removes its own sibling on any exception, and :func:`terminating_raises`
turns SIGTERM into an exception (as Python does SIGINT) for the time of the writing, so that it is cleaned
too. ``kill -9`` cannot be caught: the next writer of the same ``NAME`` removes (:func:`remove_stale`)
every ``.NAME.tmp-PID-*`` whose ``PID`` is no running process. A sibling of a live process (a
concurrent writer of the same output) is never touched; one whose PID has since been reused by
another process stays until that process ends.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import threading
import uuid
from pathlib import Path


def tmp_sibling(out: Path, suffix: str = "") -> Path:
    """``DIR/.NAME.tmp-PID-HEX[suffix]``: a fresh hidden sibling of ``out`` owned by this process."""
    return out.parent / f".{out.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}{suffix}"


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by another user
        return True
    return True


def remove_stale(out: Path) -> list[Path]:
    """Remove the temporary siblings of ``out`` left by writers that no longer run; return them."""
    out = Path(out)
    if not out.parent.is_dir():
        return []
    pattern = re.compile(rf"^\.{re.escape(out.name)}\.tmp-(\d+)-[0-9a-f]+")
    removed = []
    for p in out.parent.iterdir():
        m = pattern.match(p.name)
        if m and not _alive(int(m.group(1))):
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() and not p.is_symlink() else p.unlink(missing_ok=True)
            removed.append(p)
    return removed


def remove(path: Path) -> None:
    """Remove a file or directory tree, if there."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def replace(tmp: Path, out: Path) -> None:
    """Move the finished ``tmp`` onto ``out`` (a directory or a file), removing an old ``out``."""
    if out.exists() and out.is_dir():
        old = tmp_sibling(out)
        os.replace(out, old)
        os.replace(tmp, out)
        remove(old)
    else:
        os.replace(tmp, out)


class Terminated(BaseException):
    """Raised in the main thread when the process gets SIGTERM inside :func:`terminating_raises`."""


@contextlib.contextmanager
def terminating_raises():
    """Inside: SIGTERM raises :class:`Terminated` (as SIGINT raises ``KeyboardInterrupt``), so that
    ``except``/``finally`` clauses clean up; the previous handler is restored on exit. A no-op
    outside the main thread (where Python cannot set handlers)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Terminated(f"terminated by signal {signum}")

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


@contextlib.contextmanager
def publishing(out, suffix: str = ""):
    """Write ``out`` (a file or a directory) through a temporary sibling: removes the stale siblings
    of dead writers, yields a fresh :func:`tmp_sibling` (nothing created: the body makes the file or
    directory), moves it onto ``out`` when the body ends normally, and removes it on any exception,
    SIGTERM included (:func:`terminating_raises`)."""
    out = Path(out)
    remove_stale(out)
    tmp = tmp_sibling(out, suffix)
    with terminating_raises():
        try:
            yield tmp
            replace(tmp, out)
        except BaseException:
            remove(tmp)
            raise
