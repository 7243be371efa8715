"""A dependency-free progress line for long work: count, rate, ETA and live figures.

On a terminal it redraws one line; in a log or CI it prints a line every `every_s` seconds so
output stays short.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """Progress of `total` steps (None when unknown), written to `stream` (stderr)."""

    def __init__(
        self,
        total: int | None,
        label: str,
        unit: str = "frames",
        stream: TextIO | None = None,
        every_s: float = 5.0,
    ) -> None:
        self.total = total
        self.label = label
        self.unit = unit
        self.stream = stream if stream is not None else sys.stderr
        self.every_s = every_s
        self.tty = self.stream.isatty()
        self.start = time.perf_counter()
        self.count = 0
        # The first line waits one interval: a rate or ETA from the first step means nothing.
        self._last_print = self.start

    def update(self, count: int, **figures: float | str) -> None:
        """Record that `count` steps are done; `figures` (e.g. loss=0.1) are shown alongside."""
        self.count = count
        now = time.perf_counter()
        if now - self._last_print < (0.1 if self.tty else self.every_s):
            return
        self._last_print = now
        self._write(self._line(now, figures), final=False)

    def close(self, **figures: float | str) -> float:
        """Print the final line; returns the elapsed seconds."""
        now = time.perf_counter()
        self._write(self._line(now, figures), final=True)
        return now - self.start

    def _line(self, now: float, figures: dict) -> str:
        elapsed = now - self.start
        rate = self.count / elapsed if elapsed > 0 else 0.0
        if self.total:
            bar_len = 24
            filled = int(bar_len * min(self.count, self.total) / self.total)
            head = (
                f"{self.label} [{'#' * filled}{'.' * (bar_len - filled)}] {self.count}/{self.total}"
            )
            if 0 < self.count < self.total and rate > 0:
                head += f" eta {(self.total - self.count) / rate:.0f}s"
        else:
            head = f"{self.label} {self.count}"
        text = f"{head} {rate:.1f} {self.unit}/s {elapsed:.1f}s"
        if figures:
            text += " " + " ".join(f"{k}={_fmt(v)}" for k, v in figures.items())
        return text

    def _write(self, line: str, final: bool) -> None:
        if self.tty:
            self.stream.write("\r\033[2K" + line + ("\n" if final else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()


def _fmt(value: float | str) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)
