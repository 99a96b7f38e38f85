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

Before the work: :func:`check_writable` meets the error that writing an output would (a read-only folder, a
path under a file) by creating and removing a file where it would go, and :func:`check_space` / :func:`reserve`
the full disk, so that a file written through a memory map never finds it full (a page that cannot be
stored is a SIGBUS, "Bus error", which no ``except`` catches and which leaves the sibling behind).
"""

from __future__ import annotations

import contextlib
import errno
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
    removed = [p for p in out.parent.iterdir() if (m := pattern.match(p.name)) and not _alive(int(m.group(1)))]
    for p in removed:
        remove(p)
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
    """Write ``out`` (a file or a directory) through a temporary sibling: makes ``out``'s missing parent folders,
    removes the stale siblings of dead writers, yields a fresh :func:`tmp_sibling` (nothing created: the body makes
    the file or directory), moves it onto ``out`` when the body ends normally, and removes it on any exception,
    SIGTERM included (:func:`terminating_raises`); an ``OSError`` that names no file (a write to an open one: a
    full disk) is raised again naming ``out``."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    remove_stale(out)
    tmp = tmp_sibling(out, suffix)
    with terminating_raises():
        try:
            yield tmp
            replace(tmp, out)
        except OSError as err:
            remove(tmp)
            if err.filename is None and err.errno is not None:  # a write to an open file: name what it was writing
                raise OSError(err.errno, err.strerror or str(err), str(out)) from err
            raise
        except BaseException:
            remove(tmp)
            raise


def check_writable(out, kind: str = "file") -> None:
    """Raise the ``OSError`` that writing ``out`` would meet, before any work, naming the path: ``kind`` ``"file"``
    (written whole: not a folder), ``"folder"`` (a folder written whole, through a sibling) or ``"into"`` (a folder
    that files are written into: not a file). A file is created and removed where the writing would create one
    (in ``out`` for ``"into"``, else beside it; in the nearest existing folder above where folders are missing,
    none of which is made here)."""
    out = Path(out)
    if kind == "file" and out.is_dir():
        raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(out))
    if kind == "into" and out.exists() and not out.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(out))
    folder = out if kind == "into" else out.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(folder))
    probe = tmp_sibling(folder / out.name, ".probe")
    try:
        probe.open("x").close()
    except OSError as err:
        raise type(err)(err.errno, f"{err.strerror}, so {out.name} cannot be written there", str(folder)) from None
    probe.unlink()


def _size(nbytes: int) -> str:
    return f"{nbytes / 1e6:.1f} MB" if nbytes >= 1e5 else f"{nbytes} bytes"


def check_space(directory, nbytes: int, what: str) -> None:
    """An ``OSError`` (``ENOSPC``) naming ``directory`` unless its file system has ``nbytes`` free for ``what``."""
    free = shutil.disk_usage(directory).free
    if nbytes > free:
        raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)}: {what} needs {_size(nbytes)}, {_size(free)} free",
                      str(directory))


def reserve(file, nbytes: int) -> None:
    """Allocate the disk blocks of the first ``nbytes`` of ``file`` (``posix_fallocate``), so that writing them
    through a memory map cannot find the disk full; an ``OSError`` naming the file where they cannot be had. Where
    the file system or the platform cannot allocate ahead, :func:`check_space` is the check instead."""
    if nbytes <= 0:
        return
    fd = os.open(file, os.O_RDWR)
    try:
        os.posix_fallocate(fd, 0, nbytes)
    except (AttributeError, OSError) as err:  # AttributeError: no posix_fallocate on this platform
        if isinstance(err, OSError) and err.errno not in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
            raise OSError(err.errno, err.strerror, str(file)) from None
        check_space(Path(file).parent, nbytes - os.fstat(fd).st_blocks * 512, Path(file).name)
    finally:
        os.close(fd)
