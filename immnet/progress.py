"""Progress of long loops (data generation, a data set's merge, evaluation): tqdm's bar on a terminal; in a log
file or a pipe, where a bar's carriage returns make one unreadable line, plain lines instead: one when the loop
starts, then one whenever ``every_seconds`` (a minute) have passed since the last line, and one at its end, each
with the count done, the elapsed time and an estimate of the time left."""

from __future__ import annotations

import sys
import time


def duration(seconds: float) -> str:
    """``seconds`` as ``1h02m03s`` / ``2m05s`` / ``45s``."""
    s = int(round(seconds))
    h, m = s // 3600, s % 3600 // 60
    return f"{h}h{m:02d}m{s % 60:02d}s" if h else f"{m}m{s % 60:02d}s" if m else f"{s}s"


class LineProgress:
    """The plain-line progress of a loop of ``total`` units (see the module doc); as much of tqdm's interface
    as the package uses: iterate over it, or ``update(n)`` and ``close()``."""

    def __init__(self, iterable=None, total: int | None = None, desc: str = "", unit: str = "it", file=None,
                 every_seconds: float = 60.0, clock=time.monotonic):
        self.iterable = iterable
        self.clock = clock  # seconds
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)
        self.total, self.desc, self.unit = total, desc.strip(), unit
        self.file = file
        self.every_seconds = every_seconds
        self.n = 0
        self.start = self.last = None
        self.closed = False
        if iterable is None:  # the update form: the work starts now
            self._begin()

    def _say(self, text: str) -> None:
        print(f"[{self.desc}] {text}" if self.desc else text, file=self.file or sys.stderr, flush=True)

    def _begin(self) -> None:
        if self.start is None:
            self.start = self.last = self.clock()
            self._say(f"0/{self.total if self.total is not None else '?'} {self.unit}")

    def update(self, n: int = 1) -> None:
        self._begin()
        self.n += n
        now = self.clock()
        if now - self.last >= self.every_seconds:
            self.last = now
            elapsed = now - self.start
            left = (f", left ~{duration(elapsed / self.n * (self.total - self.n))}"
                    if self.total is not None and self.n > 0 else "")
            self._say(f"{self.n}/{self.total if self.total is not None else '?'} {self.unit}, elapsed "
                      f"{duration(elapsed)}{left}")

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._begin()
        self._say(f"{self.n} {self.unit} in {duration(self.clock() - self.start)}")

    def __iter__(self):
        self._begin()
        for item in self.iterable:
            yield item
            self.update(1)
        self.close()


def progress(iterable=None, total: int | None = None, desc: str = "", unit: str = "it", file=None,
             disable: bool = False, clock=time.monotonic, **tqdm_kwargs):
    """A progress bar over ``iterable`` (or for ``total`` units, advanced by ``update``): tqdm when ``file``
    (stderr by default) is a terminal, else :class:`LineProgress` (reading ``clock``); ``disable`` shows nothing."""
    stream = file or sys.stderr
    if disable or (hasattr(stream, "isatty") and stream.isatty()):
        from tqdm import tqdm

        return tqdm(iterable, total=total, desc=desc, unit=unit, file=stream, disable=disable, **tqdm_kwargs)
    return LineProgress(iterable, total=total, desc=desc, unit=unit, file=stream, clock=clock)
