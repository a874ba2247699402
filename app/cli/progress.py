"""The progress of a long command on stderr: a bar on a terminal, a plain line every few seconds elsewhere.

On a terminal, tqdm draws a bar with the total, the rate and the time left; lines said meanwhile go
above it. Anywhere else (a log file, a CI job, a pipe) the same figures come as a plain line every
``PLAIN_EVERY_S`` seconds and at the end of each stage. The importers and the backup use it, in
stages (a bag's sizing pass, then its fusion).
"""

from __future__ import annotations

import os
import sys
import time
from types import TracebackType
from typing import Self, TextIO

from tqdm import tqdm

#: Seconds between two plain progress lines (not on a terminal).
PLAIN_EVERY_S = 5.0


def _columns(stream: TextIO) -> int:
    """The width of the terminal ``stream`` writes to; 0 when it does not say."""
    try:
        return os.get_terminal_size(stream.fileno()).columns
    except (OSError, ValueError):
        return 0


class Progress:
    """Stages of counted work (``stage``, ``update``), and lines between them (``say``), on ``stream``.

    A context manager: leaving it ends the current stage, so that an error or an interruption is
    said on a line of its own, below the last figures.
    """

    def __init__(self, prog: str, stream: TextIO | None = None, *, every_s: float = PLAIN_EVERY_S) -> None:
        self.prog, self.stream, self.every_s = prog, stream or sys.stderr, every_s
        self.terminal = self.stream.isatty()
        self._bar: tqdm | None = None
        self._what = self._unit = self._note = ""
        self._total = self._done = self._last_done = 0
        self._started = self._last = 0.0
        self._shown = True  # no stage yet: nothing to show at its end

    def stage(self, what: str, total: int, unit: str) -> None:
        """Start counting ``total`` ``unit`` of ``what`` (e.g. ``fusing``, 237, ``scans``), ending the stage before."""
        self.close()
        self._what, self._total, self._unit, self._done, self._last_done, self._note = what, total, unit, 0, 0, ""
        self._started = self._last = time.perf_counter()
        self._shown = False
        if self.terminal:
            # a terminal that does not say its width (a pty without a size) would get a bar of no columns
            sized = _columns(self.stream) > 0
            self._bar = tqdm(total=total, desc=f"{self.prog}: {what}", unit=unit, file=self.stream,
                             dynamic_ncols=sized, ncols=None if sized else 100)

    def update(self, done: int, note: str = "") -> None:
        """``done`` of the stage's total so far; ``note``: what else to show (``5,792 rays``)."""
        self._done, self._note, self._shown = done, note, False
        if self._bar is not None:
            self._bar.set_postfix_str(note, refresh=False)
            self._bar.update(done - self._bar.n)
        elif time.perf_counter() - self._last >= self.every_s:
            self._plain_line()

    def say(self, text: str) -> None:
        """A line of its own, ``PROG: text`` (above the bar on a terminal)."""
        line = f"{self.prog}: {text}"
        if self._bar is not None:
            self._bar.write(line, file=self.stream)
        else:
            print(line, file=self.stream, flush=True)

    def close(self) -> None:
        """End the stage: its bar stays as it stands, or its last figures get their plain line."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        elif not self._shown:
            self._plain_line()
        self._shown = True

    def _plain_line(self) -> None:
        """The figures; the rate (and so the time left) of the work since the line before, as a first compilation
        or a slow start would otherwise weigh on every later estimate (of the whole stage when none was done since)."""
        now = time.perf_counter()
        since, base = (self._last, self._last_done) if self._done > self._last_done else (self._started, 0)
        rate = (self._done - base) / (now - since) if now > since else 0.0
        self._last, self._last_done, self._shown = now, self._done, True
        speed = f"{rate:,.0f}" if rate >= 10 else f"{rate:.1f}"
        left = tqdm.format_interval((self._total - self._done) / rate) if rate > 0 else "?"
        note = f", {self._note}" if self._note else ""
        print(f"{self.prog}: {self._what}: {self._done:,}/{self._total:,} {self._unit}{note}; {speed} {self._unit}/s, "
              f"{tqdm.format_interval(now - self._started)} elapsed, {left} left", file=self.stream, flush=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.close()
