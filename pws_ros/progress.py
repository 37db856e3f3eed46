"""A small progress bar with an ETA on stderr (no tqdm).

It draws only on a terminal: when the stream is not a TTY (CI logs, pipes) or when ``enabled=False``
(``--quiet``) nothing is written at all, so output files and captured logs stay clean. Redraws are
rate-limited (``min_interval`` seconds) and the bar never wraps (it fits the terminal width).

    bar = ProgressBar(total=36, label="replay")
    for ...:
        bar.update(1, note="tz certified")
    bar.close()
"""
from __future__ import annotations

import math
import shutil
import sys
import time
from typing import Callable, TextIO


def format_duration(seconds: float) -> str:
    """``H:MM:SS`` or ``M:SS`` ("?" for an unknown / infinite duration)."""
    if seconds is None or not math.isfinite(seconds) or seconds < 0:
        return "?"
    s = int(round(seconds))
    h, rem = divmod(s, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def eta_seconds(count: int, total: int | None, elapsed: float) -> float:
    """Remaining time at the mean rate so far (NaN when unknown: no total or nothing done yet)."""
    if total is None or count <= 0 or elapsed <= 0:
        return float("nan")
    return max(0.0, elapsed / count * (total - count))


def format_bar(count: int, total: int | None, elapsed: float, *, label: str = "", note: str = "", width: int = 80,
               unit: str = "frames") -> str:
    """One line: ``label [#####.....] 12/36  33%  0:12 < 0:24  1.00 frames/s  note`` fitted to ``width``."""
    rate = count / elapsed if elapsed > 0 else 0.0
    head = f"{label} " if label else ""
    if total:
        frac = min(1.0, max(0.0, count / total))
        stats = (f" {count}/{total} {100 * frac:3.0f}%  {format_duration(elapsed)} < "
                 f"{format_duration(eta_seconds(count, total, elapsed))}  {rate:.2f} {unit}/s")
    else:
        frac = None
        stats = f" {count} {unit}  {format_duration(elapsed)}  {rate:.2f} {unit}/s"
    tail = f"  {note}" if note else ""
    bar = ""
    if frac is not None:
        room = width - len(head) - len(stats) - len(tail) - 2
        if room < 10:  # drop the note before the bar
            tail = ""
            room = width - len(head) - len(stats) - 2
        n = max(10, min(40, room))
        filled = int(round(frac * n))
        bar = "[" + "#" * filled + "." * (n - filled) + "]"
    line = head + bar + stats + tail
    return line[: max(1, width - 1)]


class ProgressBar:
    """Progress with ETA on ``stream`` (default stderr). ``enabled=None``: only when ``stream`` is a TTY."""

    def __init__(self, total: int | None = None, *, label: str = "", stream: TextIO | None = None,
                 enabled: bool | None = None, min_interval: float = 0.1, unit: str = "frames",
                 clock: Callable[[], float] = time.monotonic):
        self.stream = stream if stream is not None else sys.stderr
        if enabled is None:
            isatty = getattr(self.stream, "isatty", None)
            try:
                enabled = bool(isatty()) if isatty is not None else False
            except (ValueError, OSError):  # closed stream
                enabled = False
        self.enabled = bool(enabled)
        self.total = int(total) if total is not None and total > 0 else None
        self.label = label
        self.unit = unit
        self.count = 0
        self.note = ""
        self.min_interval = float(min_interval)
        self._clock = clock
        self._start = clock()
        self._last_draw = -math.inf
        self._drawn = False
        self._closed = False

    @property
    def elapsed(self) -> float:
        return self._clock() - self._start

    def set_total(self, total: int | None) -> None:
        self.total = int(total) if total is not None and total > 0 else None

    def update(self, n: int = 1, note: str | None = None) -> None:
        self.count += int(n)
        if note is not None:
            self.note = note
        self._draw()

    def set_note(self, note: str) -> None:
        self.note = note
        self._draw()

    def line(self) -> str:
        width = shutil.get_terminal_size((100, 20)).columns
        return format_bar(self.count, self.total, self.elapsed, label=self.label, note=self.note, width=width, unit=self.unit)

    def _draw(self, force: bool = False) -> None:
        if not self.enabled or self._closed:
            return
        now = self._clock()
        if not force and now - self._last_draw < self.min_interval:
            return
        self._last_draw = now
        try:
            self.stream.write("\r\x1b[2K" + self.line())
            self.stream.flush()
            self._drawn = True
        except (ValueError, OSError):
            self.enabled = False

    def clear(self) -> None:
        """Erase the bar (before printing a log line); the next update redraws it."""
        if self.enabled and self._drawn and not self._closed:
            try:
                self.stream.write("\r\x1b[2K")
                self.stream.flush()
            except (ValueError, OSError):
                self.enabled = False
            self._last_draw = -math.inf

    def close(self) -> None:
        """Draw the final state and end the line."""
        if self._closed:
            return
        if self.enabled and self._drawn:
            self._draw(force=True)
            try:
                self.stream.write("\n")
                self.stream.flush()
            except (ValueError, OSError):
                pass
        self._closed = True

    def __enter__(self) -> "ProgressBar":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["ProgressBar", "eta_seconds", "format_bar", "format_duration"]
