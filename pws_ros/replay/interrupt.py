"""SIGINT and SIGTERM as a clean stop of a long offline run (``pws replay``).

:class:`StopSignals` turns both signals into :class:`Interrupted` (a ``KeyboardInterrupt``) in the
main thread, at a safe point: never inside a :meth:`StopSignals.section` (where a frame's outputs are
written and flushed), so the frame in flight is either written whole or dropped whole. The caller
then closes its output and writes its summary for what was done. SIGKILL cannot be caught: what
survives it is what the writer flushed before (see :class:`pws_ros.bagio.BagWriter`).
"""
from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Any, Iterator

EXIT_CODES = {"SIGINT": 130, "SIGTERM": 143}


class Interrupted(KeyboardInterrupt):
    """The run was stopped by ``signame`` (SIGINT or SIGTERM)."""

    def __init__(self, signame: str):
        super().__init__(signame)
        self.signame = signame

    @property
    def exit_code(self) -> int:
        return EXIT_CODES.get(self.signame, 130)


class StopSignals:
    """``with StopSignals() as stop:`` handles SIGINT and SIGTERM until the block ends (main thread
    only; elsewhere it does nothing). The first signal raises :class:`Interrupted` at once, or at the
    end of the current :meth:`section`; later signals only record themselves (the clean-up is short)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.signame = ""
        self._critical = 0
        self._raised = False
        self._old: dict[int, Any] = {}

    def __enter__(self) -> "StopSignals":
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                self._old[sig] = signal.signal(sig, self._handler)
        return self

    def __exit__(self, *exc: Any) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old.clear()

    def _handler(self, signum: int, _frame: Any) -> None:
        if self.signame:
            return
        self.signame = signal.Signals(signum).name
        if not self._critical:
            self._raise()

    def _raise(self) -> None:
        self._raised = True
        raise Interrupted(self.signame)

    @contextmanager
    def section(self) -> Iterator[None]:
        """A block no signal interrupts; a signal that came meanwhile is raised when it ends."""
        self._critical += 1
        try:
            yield
        finally:
            self._critical -= 1
        if self.signame and not self._critical and not self._raised:
            self._raise()


__all__ = ["EXIT_CODES", "Interrupted", "StopSignals"]
