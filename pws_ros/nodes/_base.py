"""rclpy-free pieces of the node runtime that both :mod:`._ros` (the rclpy glue) and :mod:`._common`
(the node logic) use: the worker thread, the shutdown-safe publisher, the teardown that a second
Ctrl-C cannot break. Imports neither of them, so there is no import circle."""
from __future__ import annotations

import signal
import threading
import traceback
import weakref
from typing import Any, Callable

from ..bridge.sync import LatestSlot, RateMeter
from ..core.errors import PwsError

TF_MESSAGE_TYPE = "tf2_msgs/msg/TFMessage"

_WORKERS: "weakref.WeakSet[Worker]" = weakref.WeakSet()


def still_running_workers() -> list[str]:
    """The names of the :class:`Worker` threads still running after :meth:`Worker.close` was asked."""
    return sorted(w.thread.name for w in list(_WORKERS) if w.stopping and w.thread.is_alive())


class Worker:
    """A daemon thread that processes the newest item of a :class:`LatestSlot` with ``fn``.

    Exceptions never end the thread: PwsError is logged as a warning, anything else as an error
    with its traceback; ``last_error`` holds the last item's error ("" after a success).
    """

    def __init__(self, name: str, fn: Callable[[Any], None], log: Callable[[str, str], None]):
        self.slot: LatestSlot[Any] = LatestSlot()
        self.fn = fn
        self.log = log
        self.last_error = ""
        self.busy = False
        self.processed = 0
        self.rate = RateMeter()
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self.thread.start()
        _WORKERS.add(self)

    def submit(self, item: Any) -> bool:
        """Hand over the newest input; True if an older one was dropped."""
        return self.slot.put(item)

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def _loop(self) -> None:
        while not self._stop.is_set():
            item = self.slot.take(timeout=0.2)
            if item is None:
                continue
            self.busy = True
            try:
                self.fn(item)
                self.last_error = ""
                self.processed += 1
                self.rate.tick()
            except PwsError as exc:
                self.last_error = str(exc)
                self.log("warn", str(exc))
            except Exception as exc:  # keep the node alive
                self.last_error = f"{type(exc).__name__}: {exc}"
                if self.stopping:  # the node is being torn down under this frame: not an error of the frame
                    self.log("info", f"frame abandoned at shutdown ({type(exc).__name__}: {exc})")
                else:
                    self.log("error", f"worker failed: {type(exc).__name__}: {exc}\n{traceback.format_exc()}")
            finally:
                self.busy = False

    def close(self, timeout: float = 2.0) -> None:
        """Ask the thread to stop and wait up to ``timeout`` s. ``ros2 launch`` escalates to SIGTERM 5 s
        after SIGINT, so this stays short: a computation that does not see ``stopping`` in time (a
        plan on a huge cloud, an axis being certified) is abandoned: the node's process then ends
        with ``os._exit`` (:func:`still_running_workers`, ``_ros.run``)."""
        self._stop.set()
        self.slot.close()
        self.thread.join(timeout)


class WorkerNode:
    """A node's logic around one :class:`Worker` (``self.worker``), and maybe an overlay output
    (``self.overlay``, with its own): closing the node closes both."""

    worker: Worker

    def close(self) -> None:
        self.worker.close()
        overlay = getattr(self, "overlay", None)
        if overlay is not None:
            overlay.close()


class ShutdownSafePublisher:
    """A publisher that does nothing once the ROS context is shut down.

    SIGINT shuts the context down while a worker may still be certifying a frame; publishing its
    results then raised ``RCLError: Failed to publish: publisher's context is invalid``. Publishing
    is skipped (counted in ``skipped``) when ``ok()`` is False, and a publish that fails because the
    shutdown happened meanwhile is skipped too; any other failure is raised as before.
    """

    def __init__(self, publisher: Any, ok: Callable[[], bool]):
        self.publisher = publisher
        self.ok = ok
        self.skipped = 0

    def publish(self, msg: Any) -> None:
        if not self.ok():
            self.skipped += 1
            return
        try:
            self.publisher.publish(msg)
        except Exception:
            if self.ok():
                raise
            self.skipped += 1

    def __getattr__(self, name: str) -> Any:
        return getattr(self.publisher, name)


def ignore_further_interrupts() -> None:
    """From now on SIGINT does nothing: the node is already shutting down. A terminal Ctrl-C sends
    SIGINT to the whole process group and ``ros2 launch`` sends its own SIGINT after it; the second one
    raised ``KeyboardInterrupt`` inside rclpy's ``destroy_node`` (a traceback at every shutdown)."""
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    except (ValueError, OSError):  # not the main thread, or no signals here: nothing to protect
        pass


def quiet_teardown(steps: list[Callable[[], Any]], log: Callable[[str, str], None] | None = None) -> None:
    """Run every teardown step once, in order, even if an interrupt or an error hits one of them: a
    ``KeyboardInterrupt`` (a SIGINT that arrived before :func:`ignore_further_interrupts` took effect)
    is swallowed, any other exception is logged as one line and the next step runs."""
    for step in steps:
        try:
            step()
        except KeyboardInterrupt:
            continue
        except Exception as exc:  # noqa: BLE001 - shutting down: say it, go on
            if log is not None:
                try:
                    log("info", f"shutdown: {getattr(step, '__name__', 'step')} failed ({type(exc).__name__}: {exc})")
                except Exception:  # noqa: BLE001 - the logger itself may be gone
                    pass
