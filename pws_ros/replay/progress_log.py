"""Progress of a long run: a tqdm bar on a terminal, plain periodic log lines elsewhere.

``mode="bar"`` (default when the stream is a terminal) draws a tqdm bar with rate and ETA;
``mode="log"`` (default otherwise: launch files, CI jobs, ``nohup``, a pipe) writes one plain line
every ``interval_s`` seconds and one at the end, e.g.
``pws replay: 12/36 frames (33%), 0.85 frames/s, elapsed 00:14, ETA 00:28, last: tz ok, ry not cert.``;
``mode="off"`` (``--quiet``) writes nothing.

    progress = Progress(36, label="pws replay")
    for ...:
        progress.update(1, note="last: tz ok")
    progress.close()
"""
from __future__ import annotations

import math
import sys
import time
from typing import Callable, TextIO

from tqdm import tqdm

MODES = ("bar", "log", "off")
DEFAULT_INTERVAL_S = 30.0


def _is_tty(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):  # no isatty, or a closed stream
        return False


def _duration(seconds: float) -> str:
    return tqdm.format_interval(seconds) if math.isfinite(seconds) and seconds >= 0 else "?"


class Progress:
    """Progress of ``total`` items (None: unknown) on ``stream`` (default stderr).

    ``mode``: "bar", "log" or "off"; None picks "bar" on a terminal, else "log". In log mode the
    lines go to ``emit`` without the label (a logger adds its own prefix; default: printed to
    ``stream`` with the label), at most one per ``interval_s`` seconds (0: one per update) and a
    last one at :meth:`close`.
    """

    def __init__(self, total: int | None = None, *, label: str = "", unit: str = "frames", mode: str | None = None,
                 interval_s: float = DEFAULT_INTERVAL_S, stream: TextIO | None = None,
                 emit: Callable[[str], None] | None = None, clock: Callable[[], float] = time.monotonic):
        self.stream = stream if stream is not None else sys.stderr
        if mode is None:
            mode = "bar" if _is_tty(self.stream) else "log"
        if mode not in MODES:
            raise ValueError(f"progress mode must be one of {', '.join(MODES)}, got {mode!r}")
        self.mode = mode
        self.label = label
        self.unit = unit
        self.total = int(total) if total is not None and total > 0 else None
        self.count = 0
        self.note = ""
        self.interval_s = max(0.0, float(interval_s))
        self._emit = emit
        self._clock = clock
        self._start = clock()
        self._last_line = self._start
        self._logged_count = 0
        self._closed = False
        self._bar = None
        if mode == "bar":
            self._bar = tqdm(total=self.total, desc=label or None, unit=unit.rstrip("s") or "it", file=self.stream,
                             dynamic_ncols=True, leave=True)

    @property
    def elapsed(self) -> float:
        return self._clock() - self._start

    def set_total(self, total: int | None) -> None:
        self.total = int(total) if total is not None and total > 0 else None
        if self._bar is not None:
            self._bar.total = self.total
            self._bar.refresh()

    def set_note(self, note: str) -> None:
        self.note = note
        if self._bar is not None:
            self._bar.set_postfix_str(note, refresh=False)

    def update(self, n: int = 1, note: str | None = None) -> None:
        if note is not None:
            self.set_note(note)
        self.count += int(n)
        if self._bar is not None:
            self._bar.update(int(n))
        elif self.mode == "log" and self._clock() - self._last_line >= self.interval_s:
            self._log_line()

    def update_to(self, done: int, total: int | None = None) -> None:
        """A ``progress(done, total)`` callback (the core's certification loops)."""
        if total is not None and total != self.total:
            self.set_total(total)
        self.update(int(done) - self.count)

    def line(self, label: bool = True) -> str:
        """The plain log line of the current state."""
        elapsed = self.elapsed
        rate = self.count / elapsed if elapsed > 0 else 0.0
        head = f"{self.label}: " if self.label and label else ""
        if self.total:
            done = f"{self.count}/{self.total} {self.unit} ({100.0 * self.count / self.total:.0f}%)"
            eta = (self.total - self.count) / rate if rate > 0 else float("nan")
            timing = f"elapsed {_duration(elapsed)}, ETA {_duration(eta)}"
        else:
            done = f"{self.count} {self.unit}"
            timing = f"elapsed {_duration(elapsed)}"
        return f"{head}{done}, {rate:.2f} {self.unit}/s, {timing}" + (f", {self.note}" if self.note else "")

    def _log_line(self) -> None:
        self._last_line = self._clock()
        self._logged_count = self.count
        if self._emit is not None:
            self._emit(self.line(label=False))
            return
        text = self.line()
        try:
            print(text, file=self.stream, flush=True)
        except (ValueError, OSError):  # closed stream
            self.mode = "off"

    def clear(self) -> None:
        """Erase the bar before another line is printed (the next update redraws it)."""
        if self._bar is not None:
            self._bar.clear()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._bar is not None:
            self._bar.close()
        elif self.mode == "log" and self.count != self._logged_count:
            self._log_line()

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["DEFAULT_INTERVAL_S", "MODES", "Progress"]
