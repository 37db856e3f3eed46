"""Stamp matching and the latest-only online policy (thread-safe, ROS-free).

- :class:`StampMatcher` pairs messages of several streams (depth + colour + CameraInfo) whose stamps
  agree within a tolerance, from bounded buffers; what can no longer be matched is dropped and counted.
  A stamp that jumps back starts a new timeline (:mod:`pws_ros.bridge.timejump`).
- :class:`LatestSlot` is the online policy: certification is slower than the camera, so the worker
  always takes the *newest* complete input; an input replaced before the worker took it is dropped
  and counted. Nothing is ever queued without bound.

The four-process mode's partition-set assembly is :mod:`pws_ros.bridge.assembly`.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Generic, Iterable, TypeVar

from ..core.errors import require
from .timejump import JUMP_BACK_TOLERANCE_NS, Timeline

T = TypeVar("T")


# ---- stamp matching -----------------------------------------------------------------------

@dataclass
class MatchedSet:
    """One message per stream, with their stamps (ns); ``stamp_ns`` is the reference stream's."""

    stamp_ns: int
    messages: dict[str, Any]
    stamps: dict[str, int]

    def __getitem__(self, key: str) -> Any:
        return self.messages[key]


class StampMatcher(Timeline):
    """Approximate-time matching of several streams within ``tolerance_ns``.

    ``add(stream, stamp_ns, msg)`` buffers a message (each buffer holds at most ``queue_size``;
    overflow drops the oldest) and returns a :class:`MatchedSet` as soon as every stream has a
    message whose stamp is within ``tolerance_ns`` of the reference stream's (the first of
    ``streams``; the closest candidate wins, ties go to the older one). After a match, every
    buffered message not newer than the matched ones is dropped (it can no longer be part of a
    newer set) and counted in ``dropped[stream]``. Messages with a stamp not newer than the last
    match of their stream are dropped on arrival, unless the stamp is older than the newest match
    by more than ``jump_back_tolerance_ns`` (default 1 s), or it repeats a stamp already matched on
    its stream in this timeline (a looped bag shorter than the tolerance): then time jumped back (a
    looped bag, a restarted driver), and the matcher starts over (buffers dropped and counted,
    ``time_jumps`` + 1, ``on_time_jump(text)`` called once) with this message as the first of the new
    timeline.

    With ``max_skew_ns`` above ``tolerance_ns`` (what message_filters' ApproximateTime does for unsynced
    drivers, e.g. a RealSense whose depth and colour run at different rates), a set whose stamps are
    farther apart than ``tolerance_ns`` but within ``max_skew_ns`` is matched once it is *settled*: each
    message is the nearest buffered one to its partner on the other's stream, and each of the two streams
    has a message at or after its partner's stamp (later messages, being newer, cannot be nearer); or at
    :meth:`flush` (the end of a recording). Sets within ``tolerance_ns`` match at once, as before, so
    streams that agree within it are paired exactly as without ``max_skew_ns``.
    """

    def __init__(self, streams: Iterable[str], tolerance_ns: int = 20_000_000, queue_size: int = 10,
                 jump_back_tolerance_ns: int = JUMP_BACK_TOLERANCE_NS, on_time_jump: Callable[[str], None] | None = None,
                 max_skew_ns: int = 0):
        self.streams = tuple(streams)
        require(len(self.streams) >= 1 and len(set(self.streams)) == len(self.streams), f"streams must be distinct names, got {self.streams}")
        require(int(tolerance_ns) >= 0, f"sync tolerance must be >= 0, got {tolerance_ns} ns")
        require(int(queue_size) >= 1, f"sync queue size must be >= 1, got {queue_size}")
        self.tolerance_ns = int(tolerance_ns)
        self.max_skew_ns = int(max_skew_ns)
        self._init_timeline(jump_back_tolerance_ns, on_time_jump)
        self.queue_size = int(queue_size)
        self._buffers: dict[str, deque[tuple[int, Any]]] = {s: deque() for s in self.streams}
        self._lock = threading.Lock()
        self.dropped: dict[str, int] = {s: 0 for s in self.streams}
        self.matched = 0
        self._last_match: dict[str, int] = {}
        self._matched_stamps: dict[str, deque[int]] = {s: deque(maxlen=1024) for s in self.streams}  # this timeline's

    @property
    def reference(self) -> str:
        return self.streams[0]

    def total_dropped(self) -> int:
        return sum(self.dropped.values())

    def pending(self) -> dict[str, int]:
        with self._lock:
            return {s: len(b) for s, b in self._buffers.items()}

    def add(self, stream: str, stamp_ns: int, msg: Any) -> MatchedSet | None:
        require(stream in self._buffers, f"unknown stream {stream!r}: expected one of {', '.join(self.streams)}")
        stamp_ns = int(stamp_ns)
        with self._lock:
            repeat = stamp_ns < self._last_match.get(stream, stamp_ns) and stamp_ns in self._matched_stamps[stream]
            self._jumped_back(max(self._last_match.values(), default=None), stamp_ns,
                              f"input sync ({', '.join(self.streams)})", self._restart, repeat=repeat)
            last = self._last_match.get(stream)
            if last is not None and stamp_ns <= last:
                self.dropped[stream] += 1
                return None
            buf = self._buffers[stream]
            # keep each buffer sorted by stamp (out-of-order arrivals are rare but possible)
            if buf and stamp_ns < buf[-1][0]:
                items = sorted(list(buf) + [(stamp_ns, msg)], key=lambda x: x[0])
                buf.clear()
                buf.extend(items)
            else:
                buf.append((stamp_ns, msg))
            while len(buf) > self.queue_size:
                buf.popleft()
                self.dropped[stream] += 1
            return self._try_match()

    def flush(self) -> MatchedSet | None:
        """At the end of the input (a recording): the newest set within ``max_skew_ns`` that still waits to
        be settled, if any (no later message can come to settle it)."""
        with self._lock:
            return self._try_match(flush=True)

    def _nearest(self, stream: str, stamp: int) -> tuple[int, int, Any] | None:
        """(distance, stamp, message) of the buffered message of ``stream`` nearest to ``stamp`` (ties: older)."""
        best = None
        for st, m in self._buffers[stream]:
            d = abs(st - stamp)
            if best is None or d < best[0]:
                best = (d, st, m)
        return best

    def _settled(self, stream: str, ref_stamp: int, stamp: int) -> bool:
        """Whether the pair (reference ``ref_stamp``, ``stream`` ``stamp``) can no longer be bettered: each is
        the nearest buffered to the other, and each stream holds a message at or after the other's stamp."""
        ref = self.reference
        nearest_ref = self._nearest(ref, stamp)
        return (nearest_ref is not None and nearest_ref[1] == ref_stamp
                and self._buffers[stream][-1][0] >= ref_stamp and self._buffers[ref][-1][0] >= stamp)

    def _try_match(self, flush: bool = False) -> MatchedSet | None:
        ref = self._buffers[self.reference]
        reach = max(self.tolerance_ns, self.max_skew_ns)
        # newest reference message first: the online policy prefers fresh sets
        for ref_stamp, ref_msg in reversed(ref):
            chosen: dict[str, tuple[int, Any]] = {self.reference: (ref_stamp, ref_msg)}
            for s in self.streams[1:]:
                best = self._nearest(s, ref_stamp)
                if best is None or best[0] > reach:
                    break
                if best[0] > self.tolerance_ns and not (flush or self._settled(s, ref_stamp, best[1])):
                    break
                chosen[s] = (best[1], best[2])
            else:
                for s, (st, m) in chosen.items():
                    buf = self._buffers[s]
                    taken = False
                    while buf and buf[0][0] <= st:
                        _old, old_msg = buf.popleft()
                        if not taken and old_msg is m:
                            taken = True
                        else:
                            self.dropped[s] += 1
                    self._last_match[s] = st
                    self._matched_stamps[s].append(st)
                self.matched += 1
                return MatchedSet(ref_stamp, {s: m for s, (_, m) in chosen.items()}, {s: st for s, (st, _) in chosen.items()})
        return None

    def _drop_buffered(self) -> None:
        for s, b in self._buffers.items():
            self.dropped[s] += len(b)
            b.clear()

    def _restart(self, back_ns: int) -> None:
        self._drop_buffered()
        self._last_match.clear()
        for d in self._matched_stamps.values():
            d.clear()

    def clear(self) -> None:
        with self._lock:
            self._drop_buffered()


# ---- online policy ------------------------------------------------------------------------

class LatestSlot(Generic[T]):
    """A one-item mailbox between callbacks and a worker thread.

    ``put`` stores an item, replacing (dropping, counted in ``dropped``) one the worker has not taken
    yet; ``take`` blocks until an item is there (or ``timeout`` seconds pass, or :meth:`close`) and
    returns it, or None. Memory is bounded by one item whatever the input rate.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: T | None = None
        self._full = False
        self._closed = False
        self.accepted = 0
        self.dropped = 0
        self.taken = 0

    def put(self, item: T) -> bool:
        """Store ``item``; True if an older untaken item was dropped to make room."""
        return self.replace(item)[0]

    def replace(self, item: T) -> tuple[bool, T | None]:
        """Store ``item``; (whether an older untaken item was dropped, that item)."""
        with self._cond:
            dropped, old = self._full, (self._item if self._full else None)
            if dropped:
                self.dropped += 1
            self._item, self._full = item, True
            self.accepted += 1
            self._cond.notify_all()
            return dropped, old

    def take(self, timeout: float | None = None) -> T | None:
        with self._cond:
            if not self._full and not self._closed:
                self._cond.wait_for(lambda: self._full or self._closed, timeout=timeout)
            if not self._full:
                return None
            item, self._item, self._full = self._item, None, False
            self.taken += 1
            return item

    def peek_full(self) -> bool:
        with self._cond:
            return self._full

    def close(self) -> None:
        """Wake a waiting ``take`` (it returns None once the slot is empty)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed

    def stats(self) -> dict[str, int]:
        with self._cond:
            return {"accepted": self.accepted, "dropped": self.dropped, "taken": self.taken, "pending": int(self._full)}


class RateMeter:
    """Events per second over a sliding window of the last ``window`` events (monotonic clock)."""

    def __init__(self, window: int = 20, clock: Callable[[], float] = time.monotonic):
        self._times: deque[float] = deque(maxlen=max(2, int(window)))
        self._clock = clock
        self._lock = threading.Lock()

    def tick(self, now: float | None = None) -> None:
        with self._lock:
            self._times.append(self._clock() if now is None else float(now))

    def rate(self, now: float | None = None) -> float:
        with self._lock:
            if len(self._times) < 2:
                return 0.0
            span = self._times[-1] - self._times[0]
            return (len(self._times) - 1) / span if span > 0 else 0.0



__all__ = ["JUMP_BACK_TOLERANCE_NS", "LatestSlot", "MatchedSet", "RateMeter", "StampMatcher"]
