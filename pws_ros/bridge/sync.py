"""Stamp matching, the latest-only online policy and partition-set assembly (thread-safe, ROS-free).

- :class:`StampMatcher` pairs messages of several streams (depth + colour + CameraInfo) whose stamps
  agree within a tolerance, from bounded buffers; what can no longer be matched is dropped and counted.
- :class:`LatestSlot` is the online policy: certification is slower than the camera, so the worker
  always takes the *newest* complete input; an input replaced before the worker took it is dropped
  and counted. Nothing is ever queued without bound.
- :class:`PartitionAssembler` (four-process mode) collects the rendered frames and bounds of each
  ``(stamp, axis)`` by index against the expected count; a lost (gap), duplicate or out-of-range
  index, a count that disagrees with the plan, or a timeout makes the set *failed*: an incomplete
  partition set is never certified.

Time that jumps back (``ros2 bag play --loop``, a restarted driver, a reset simulation clock): every
stamp-ordered piece here treats a stamp more than ``jump_back_tolerance_ns`` (default
:data:`JUMP_BACK_TOLERANCE_NS`, 1 s) older than its newest match/frame as a new timeline, as tf2
does: it counts the jump in ``time_jumps``, reports it once through ``on_time_jump(text)`` (the
nodes log it as WARN) and resets, so the new pass is matched and certified instead of being dropped
as "late" forever. What was buffered from before the jump is dropped and counted (the assembler
releases its incomplete sets as failed), so every input frame is still either answered or counted.
:class:`LatestSlot` keeps no stamps and needs no reset.
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any, Callable, Generic, Iterable, TypeVar

from ..core.errors import require

T = TypeVar("T")

JUMP_BACK_TOLERANCE_NS = 1_000_000_000
"""A stamp older than the newest match/frame by more than this (1 s) starts a new timeline."""


def _jump_text(what: str, back_ns: int, stamp_ns: int) -> str:
    return (f"{what}: time jumped back by {back_ns / 1e9:.3f} s (to stamp {stamp_ns}; a looped bag, a restarted "
            f"driver or a reset clock): starting over, what was buffered before the jump is dropped")


# ---- stamp matching -----------------------------------------------------------------------

@dataclass
class MatchedSet:
    """One message per stream, with their stamps (ns); ``stamp_ns`` is the reference stream's."""

    stamp_ns: int
    messages: dict[str, Any]
    stamps: dict[str, int]

    def __getitem__(self, key: str) -> Any:
        return self.messages[key]


class StampMatcher:
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
    """

    def __init__(self, streams: Iterable[str], tolerance_ns: int = 20_000_000, queue_size: int = 10,
                 jump_back_tolerance_ns: int = JUMP_BACK_TOLERANCE_NS, on_time_jump: Callable[[str], None] | None = None):
        self.streams = tuple(streams)
        require(len(self.streams) >= 1 and len(set(self.streams)) == len(self.streams), f"streams must be distinct names, got {self.streams}")
        require(int(tolerance_ns) >= 0, f"sync tolerance must be >= 0, got {tolerance_ns} ns")
        require(int(queue_size) >= 1, f"sync queue size must be >= 1, got {queue_size}")
        require(int(jump_back_tolerance_ns) >= 0, f"jump-back tolerance must be >= 0, got {jump_back_tolerance_ns} ns")
        self.tolerance_ns = int(tolerance_ns)
        self.jump_back_tolerance_ns = int(jump_back_tolerance_ns)
        self.on_time_jump = on_time_jump
        self.time_jumps = 0
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
            if self._last_match:
                newest = max(self._last_match.values())
                repeat = stamp_ns < self._last_match.get(stream, stamp_ns) and stamp_ns in self._matched_stamps[stream]
                if stamp_ns < newest - self.jump_back_tolerance_ns or repeat:
                    self._restart(newest - stamp_ns, stamp_ns)
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

    def _try_match(self) -> MatchedSet | None:
        ref = self._buffers[self.reference]
        # newest reference message first: the online policy prefers fresh sets
        for ref_stamp, ref_msg in reversed(ref):
            chosen: dict[str, tuple[int, Any]] = {self.reference: (ref_stamp, ref_msg)}
            for s in self.streams[1:]:
                best = None
                for st, m in self._buffers[s]:
                    d = abs(st - ref_stamp)
                    if d <= self.tolerance_ns and (best is None or d < best[0]):
                        best = (d, st, m)
                if best is None:
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

    def _restart(self, back_ns: int, stamp_ns: int) -> None:
        for s, b in self._buffers.items():
            self.dropped[s] += len(b)
            b.clear()
        self._last_match.clear()
        for d in self._matched_stamps.values():
            d.clear()
        self.time_jumps += 1
        if self.on_time_jump is not None:
            self.on_time_jump(_jump_text(f"input sync ({', '.join(self.streams)})", back_ns, stamp_ns))

    def clear(self) -> None:
        with self._lock:
            for s, b in self._buffers.items():
                self.dropped[s] += len(b)
                b.clear()


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
        with self._cond:
            dropped = self._full
            if dropped:
                self.dropped += 1
            self._item, self._full = item, True
            self.accepted += 1
            self._cond.notify_all()
            return dropped

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


# ---- partition-set assembly ---------------------------------------------------------------

@dataclass
class AxisSet:
    """The frames and bounds of one ``(stamp, axis)``; ``error`` is non-empty when it failed."""

    stamp_ns: int
    axis: str
    count: int
    frames: list[Any] | None = None     # index order, complete
    bounds: Any = None
    info: Any = None                    # what the plan said about this axis (opaque)
    error: str = ""

    @property
    def ok(self) -> bool:
        return not self.error


@dataclass
class AssembledFrame:
    """Everything about one input frame: one :class:`AxisSet` per expected axis, in plan order."""

    stamp_ns: int
    axes: list[AxisSet]
    info: Any = None

    @property
    def complete(self) -> bool:
        return all(a.ok for a in self.axes)


@dataclass
class _Group:
    count: int | None = None            # from the plan (authoritative) or the first frame tag
    tag_count: int | None = None
    frames: dict[int, Any] = field(default_factory=dict)
    next_index: int = 0
    bounds: Any = None
    has_bounds: bool = False
    info: Any = None
    error: str = ""
    expected: bool = False              # the plan announced it


@dataclass
class _Frame:
    created: float
    axes: "OrderedDict[str, _Group]" = field(default_factory=OrderedDict)
    expected_axes: list[str] | None = None
    info: Any = None


class PartitionAssembler:
    """Collect rendered frames by ``(stamp, axis, index)`` and release whole input frames.

    Call :meth:`expect` when the plan of an input frame arrives (``{axis: count}``, or an error string
    for an axis the planner could not plan), :meth:`add_frame` per rendered frame (its tag gives
    ``index`` and ``count``; frames of one axis arrive in index order on one topic), and
    :meth:`add_bounds` when the axis' bounds arrive. :meth:`pop_ready` returns every input frame
    whose axes are all resolved: complete, or failed (lost frame = gap in the index sequence,
    duplicate or out-of-range index, count disagreeing with the plan, or no completion within
    ``timeout_s``). At most ``max_pending`` input frames are held; a newer one evicts the oldest
    (which is released as failed). Data for a stamp already released is ignored and counted in
    ``late``, unless the stamp is older than the newest one seen by more than
    ``jump_back_tolerance_ns`` (default 1 s): then time jumped back (a looped bag, a restarted
    driver), the pending sets are released as failed, the released stamps are forgotten,
    ``time_jumps`` + 1 and ``on_time_jump(text)`` is called once, so the new pass is assembled again.
    A plan (:meth:`expect`) for a stamp already released is such a jump too: the planner plans each
    input frame once, so the stamp came again (a looped bag shorter than the tolerance).
    """

    def __init__(self, timeout_s: float = 10.0, max_pending: int = 4, clock: Callable[[], float] = time.monotonic,
                 expect_bounds: bool = True, jump_back_tolerance_ns: int = JUMP_BACK_TOLERANCE_NS,
                 on_time_jump: Callable[[str], None] | None = None):
        require(timeout_s > 0, f"assembly timeout must be positive, got {timeout_s}")
        require(int(max_pending) >= 1, f"max_pending must be >= 1, got {max_pending}")
        self.timeout_s = float(timeout_s)
        self.max_pending = int(max_pending)
        self.expect_bounds = bool(expect_bounds)
        require(int(jump_back_tolerance_ns) >= 0, f"jump-back tolerance must be >= 0, got {jump_back_tolerance_ns} ns")
        self.jump_back_tolerance_ns = int(jump_back_tolerance_ns)
        self.on_time_jump = on_time_jump
        self.time_jumps = 0
        self._newest: int | None = None
        self._clock = clock
        self._frames: "OrderedDict[int, _Frame]" = OrderedDict()
        self._released: deque[int] = deque(maxlen=256)
        self._ready: list[AssembledFrame] = []
        self._lock = threading.Lock()
        self.late = 0          # messages for a frame already released
        self.failed = 0        # axis sets released as failed
        self.completed = 0     # axis sets released complete

    # -- input --
    def _frame(self, stamp_ns: int, plan: bool = False) -> _Frame | None:
        if self._newest is not None and (stamp_ns < self._newest - self.jump_back_tolerance_ns or (plan and stamp_ns in self._released)):
            back = self._newest - stamp_ns
            for old in list(self._frames):
                self._release(old, f"time jumped back by {back / 1e9:.3f} s before it was complete")
            self._released.clear()
            self._newest = None
            self.time_jumps += 1
            if self.on_time_jump is not None:
                self.on_time_jump(_jump_text("partition assembly", back, stamp_ns))
        self._newest = stamp_ns if self._newest is None else max(self._newest, stamp_ns)
        if stamp_ns in self._released:
            self.late += 1
            return None
        fr = self._frames.get(stamp_ns)
        if fr is None:
            fr = _Frame(created=self._clock())
            self._frames[stamp_ns] = fr
            # keep insertion order sorted by stamp
            if len(self._frames) > 1 and stamp_ns < max(self._frames):
                items = sorted(self._frames.items())
                self._frames.clear()
                self._frames.update(items)
            while len(self._frames) > self.max_pending:
                old = next(iter(self._frames))
                self._release(old, f"evicted: {self.max_pending} newer input frame(s) arrived before it was complete")
        return fr

    def expect(self, stamp_ns: int, axes: dict[str, int | str], info: Any = None, axis_info: dict[str, Any] | None = None) -> None:
        """The plan of input frame ``stamp_ns``: ``{axis: frame count}`` or ``{axis: "error text"}``."""
        with self._lock:
            fr = self._frame(int(stamp_ns), plan=True)
            if fr is None:
                return
            fr.expected_axes = list(axes)
            fr.info = info
            for axis, spec in axes.items():
                g = fr.axes.setdefault(axis, _Group())
                g.expected = True
                g.info = (axis_info or {}).get(axis)
                if isinstance(spec, str):
                    g.error = g.error or spec
                    continue
                count = int(spec)
                if count < 1:
                    g.error = g.error or f"the plan has {count} frames"
                    continue
                g.count = count
                if g.tag_count is not None and g.tag_count != count:
                    g.error = g.error or f"frame tags say {g.tag_count} frames but the plan has {count}"
                bad = [i for i in g.frames if i >= count]
                if bad and not g.error:
                    g.error = f"frame index {bad[0]} out of range for {count} frames"
            self._check(int(stamp_ns))

    def add_frame(self, stamp_ns: int, axis: str, index: int, count: int, frame: Any) -> None:
        with self._lock:
            stamp_ns, index, count = int(stamp_ns), int(index), int(count)
            fr = self._frame(stamp_ns)
            if fr is None:
                return
            if fr.expected_axes is not None and axis not in fr.expected_axes:
                g = fr.axes.setdefault(axis, _Group())
                g.error = g.error or f"frame for axis {axis!r} that the plan does not list"
                return
            g = fr.axes.setdefault(axis, _Group())
            if g.error:
                return
            if g.tag_count is None:
                g.tag_count = count
            limit = g.count if g.count is not None else g.tag_count
            if count != g.tag_count or (g.count is not None and count != g.count):
                g.error = f"frame {index} says {count} frames but {limit} are expected"
            elif not 0 <= index < limit:
                g.error = f"frame index {index} out of range for {limit} frames"
            elif index in g.frames:
                g.error = f"duplicate frame index {index}"
            elif index > g.next_index:
                missing = list(range(g.next_index, index))
                g.error = f"lost frame(s) {_ranges(missing)} of {limit} (a later frame arrived first)"
            elif index < g.next_index:  # pragma: no cover - covered by the duplicate branch
                g.error = f"frame index {index} arrived out of order"
            else:
                g.frames[index] = frame
                g.next_index = index + 1
            self._check(stamp_ns)

    def add_bounds(self, stamp_ns: int, axis: str, count: int, bounds: Any) -> None:
        with self._lock:
            stamp_ns = int(stamp_ns)
            fr = self._frame(stamp_ns)
            if fr is None:
                return
            g = fr.axes.setdefault(axis, _Group())
            if g.has_bounds:
                g.error = g.error or "duplicate bounds message"
            g.bounds, g.has_bounds = bounds, True
            limit = g.count if g.count is not None else g.tag_count
            if limit is not None and int(count) != limit:
                g.error = g.error or f"bounds are for {int(count)} frames but {limit} are expected"
            elif g.tag_count is None:
                g.tag_count = int(count)
            self._check(stamp_ns)

    def fail(self, stamp_ns: int, axis: str, reason: str) -> None:
        """Mark ``(stamp, axis)`` failed (e.g. the projector could not render it)."""
        with self._lock:
            stamp_ns = int(stamp_ns)
            fr = self._frame(stamp_ns)
            if fr is None:
                return
            g = fr.axes.setdefault(axis, _Group())
            g.error = g.error or str(reason)
            self._check(stamp_ns)

    def knows(self, stamp_ns: int) -> bool:
        """Whether ``stamp_ns`` is pending or was released."""
        with self._lock:
            return int(stamp_ns) in self._frames or int(stamp_ns) in self._released

    # -- output --
    def _group_done(self, g: _Group) -> bool:
        if g.error:
            return True
        if g.count is None:
            return False
        return len(g.frames) == g.count and (g.has_bounds or not self.expect_bounds)

    def _check(self, stamp_ns: int) -> None:
        fr = self._frames.get(stamp_ns)
        if fr is None or fr.expected_axes is None:
            return
        if all(self._group_done(fr.axes[a]) for a in fr.expected_axes):
            self._release(stamp_ns, "")

    def _release(self, stamp_ns: int, reason: str) -> None:
        fr = self._frames.pop(stamp_ns)
        self._released.append(stamp_ns)
        axes_order = fr.expected_axes if fr.expected_axes is not None else list(fr.axes)
        sets = []
        for axis in axes_order:
            g = fr.axes.get(axis, _Group())
            count = g.count if g.count is not None else (g.tag_count or 0)
            if self._group_done(g) and not g.error:
                sets.append(AxisSet(stamp_ns, axis, count, [g.frames[i] for i in range(count)], g.bounds, g.info))
                self.completed += 1
                continue
            err = g.error
            if not err:
                parts = []
                if g.count is None:
                    parts.append("no plan arrived")
                if count:
                    missing = [i for i in range(count) if i not in g.frames]
                    if missing:
                        parts.append(f"missing frame(s) {_ranges(missing)} of {count}")
                elif not g.frames:
                    parts.append("no frame arrived")
                if self.expect_bounds and not g.has_bounds:
                    parts.append("no bounds arrived")
                err = "incomplete partition set: " + ", ".join(parts or ["unknown"]) + (f" ({reason})" if reason else "")
            sets.append(AxisSet(stamp_ns, axis, count, None, None, g.info, err))
            self.failed += 1
        if sets:
            self._ready.append(AssembledFrame(stamp_ns, sets, fr.info))

    def pop_ready(self, now: float | None = None) -> list[AssembledFrame]:
        """Input frames now resolved (complete or failed), oldest first; times out stale ones."""
        with self._lock:
            now = self._clock() if now is None else float(now)
            for stamp in [s for s, fr in self._frames.items() if now - fr.created >= self.timeout_s]:
                self._release(stamp, f"timed out after {self.timeout_s:g} s")
            out, self._ready = self._ready, []
            return out

    def pending(self) -> list[int]:
        with self._lock:
            return list(self._frames)


def _ranges(indices: list[int]) -> str:
    """``[1, 2, 3, 7]`` -> ``"1-3, 7"`` (at most 6 runs shown)."""
    runs: list[tuple[int, int]] = []
    for i in sorted(indices):
        if runs and i == runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], i)
        else:
            runs.append((i, i))
    text = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs[:6])
    return text + (f", ... ({len(indices)} in all)" if len(runs) > 6 else "")


__all__ = ["AssembledFrame", "AxisSet", "LatestSlot", "MatchedSet", "PartitionAssembler", "RateMeter", "StampMatcher"]
