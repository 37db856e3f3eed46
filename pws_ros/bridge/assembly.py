"""Partition-set assembly (four-process mode, thread-safe, ROS-free).

:class:`PartitionAssembler` collects the rendered frames and bounds of each ``(stamp, axis)`` by
index against the expected count; a lost (gap), duplicate or out-of-range index, a count that
disagrees with the plan, or a timeout makes the set *failed*: an incomplete partition set is never
certified. A stamp that jumps back starts a new timeline (:mod:`pws_ros.bridge.timejump`).

Anyone on the graph can publish on the four-process topics, so nothing here is sized by a message:
counts above ``max_count`` (``max_partitions``) are refused, lost or missing indices are described by
their runs (never enumerated), and the frames held for one ``(stamp, axis)`` stay within ``max_bytes``
(a set that would pass it fails, naming the ceiling, and its frames are freed), so at most
``max_pending`` x axes x ``max_bytes`` is held.
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any, Callable

from ..core.errors import require
from .timejump import JUMP_BACK_TOLERANCE_NS, Timeline


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
    nbytes: int = 0                     # memory of the frames held
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


class PartitionAssembler(Timeline):
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
                 on_time_jump: Callable[[str], None] | None = None, max_count: int | None = None,
                 max_bytes: int | None = None):
        require(timeout_s > 0, f"assembly timeout must be positive, got {timeout_s}")
        require(int(max_pending) >= 1, f"max_pending must be >= 1, got {max_pending}")
        self.timeout_s = float(timeout_s)
        self.max_pending = int(max_pending)
        self.max_count = None if max_count is None else int(max_count)   # most frames per (stamp, axis)
        self.max_bytes = None if max_bytes is None else int(max_bytes)   # most bytes of frames held in all
        self.expect_bounds = bool(expect_bounds)
        self._init_timeline(jump_back_tolerance_ns, on_time_jump)
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
        self._jumped_back(self._newest, stamp_ns, "partition assembly", self._restart,
                          repeat=plan and stamp_ns in self._released)
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

    def _restart(self, back_ns: int) -> None:
        for old in list(self._frames):
            self._release(old, f"time jumped back by {back_ns / 1e9:.3f} s before it was complete")
        self._released.clear()
        self._newest = None

    @staticmethod
    def _fail(g: _Group, reason: str) -> None:
        """Mark ``g`` failed (the first reason stays) and free the frames it held."""
        g.error = g.error or reason
        g.frames.clear()
        g.nbytes = 0

    def held_bytes(self) -> int:
        """Bytes of the frames held for every pending input frame."""
        with self._lock:
            return sum(g.nbytes for fr in self._frames.values() for g in fr.axes.values())

    def _too_many(self, count: int) -> str:
        if self.max_count is not None and count > self.max_count:
            return f"{count} frames announced, more than max_partitions {self.max_count}"
        return ""

    def _group(self, stamp_ns: int, axis: str) -> _Group | None:
        """The group of ``(stamp, axis)`` (created if new); None for a stamp already released."""
        fr = self._frame(stamp_ns)
        return None if fr is None else fr.axes.setdefault(axis, _Group())

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
                    self._fail(g, spec)
                    continue
                count = int(spec)
                if count < 1 or self._too_many(count):
                    self._fail(g, self._too_many(count) or f"the plan has {count} frames")
                    continue
                g.count = count
                if g.tag_count is not None and g.tag_count != count:
                    self._fail(g, f"frame tags say {g.tag_count} frames but the plan has {count}")
                bad = [i for i in g.frames if i >= count]
                if bad and not g.error:
                    self._fail(g, f"frame index {bad[0]} out of range for {count} frames")
            self._check(int(stamp_ns))

    def add_frame(self, stamp_ns: int, axis: str, index: int, count: int, frame: Any) -> None:
        with self._lock:
            stamp_ns, index, count = int(stamp_ns), int(index), int(count)
            fr = self._frame(stamp_ns)
            if fr is None:
                return
            if fr.expected_axes is not None and axis not in fr.expected_axes:
                g = fr.axes.setdefault(axis, _Group())
                self._fail(g, f"frame for axis {axis!r} that the plan does not list")
                return
            g = fr.axes.setdefault(axis, _Group())
            if g.error:
                return
            if self._too_many(count) or count < 1:
                self._fail(g, f"frame {index}: " + (self._too_many(count) or f"count {count}"))
                self._check(stamp_ns)
                return
            if g.tag_count is None:
                g.tag_count = count
            limit = g.count if g.count is not None else g.tag_count
            nbytes = int(getattr(frame, "nbytes", 0) or 0)
            if count != g.tag_count or (g.count is not None and count != g.count):
                self._fail(g, f"frame {index} says {count} frames but {limit} are expected")
            elif not 0 <= index < limit:
                self._fail(g, f"frame index {index} out of range for {limit} frames")
            elif index in g.frames:
                self._fail(g, f"duplicate frame index {index}")
            elif index > g.next_index:
                self._fail(g, f"lost frame(s) {_span(g.next_index, index)} of {limit} (a later frame arrived first)")
            elif index < g.next_index:  # pragma: no cover - covered by the duplicate branch
                self._fail(g, f"frame index {index} arrived out of order")
            elif self.max_bytes is not None and g.nbytes + nbytes > self.max_bytes:
                self._fail(g, f"the frames of this axis would need more than {self.max_bytes / 2**20:.0f} MiB "
                              f"(half of max_memory_mb, as the planner budgets them) at frame {index} of {limit}")
            else:
                g.frames[index] = frame
                g.nbytes += nbytes
                g.next_index = index + 1
            self._check(stamp_ns)

    def add_bounds(self, stamp_ns: int, axis: str, count: int, bounds: Any) -> None:
        with self._lock:
            stamp_ns = int(stamp_ns)
            g = self._group(stamp_ns, axis)
            if g is None:
                return
            if g.has_bounds:
                self._fail(g, "duplicate bounds message")
            g.bounds, g.has_bounds = bounds, True
            limit = g.count if g.count is not None else g.tag_count
            if self._too_many(int(count)):
                self._fail(g, f"bounds: {self._too_many(int(count))}")
            elif limit is not None and int(count) != limit:
                self._fail(g, f"bounds are for {int(count)} frames but {limit} are expected")
            elif g.tag_count is None:
                g.tag_count = int(count)
            self._check(stamp_ns)

    def fail(self, stamp_ns: int, axis: str, reason: str) -> None:
        """Mark ``(stamp, axis)`` failed (e.g. the projector could not render it)."""
        with self._lock:
            stamp_ns = int(stamp_ns)
            g = self._group(stamp_ns, axis)
            if g is None:
                return
            self._fail(g, str(reason))
            self._check(stamp_ns)

    def fail_frame(self, stamp_ns: int, axes: list[str], reason: str) -> bool:
        """Every axis of input frame ``stamp_ns`` failed (e.g. a malformed plan named it): the axes its
        plan expects, else ``axes`` and any that data arrived for. False (and counted in ``late``) for a
        stamp already released: its one certification is out."""
        with self._lock:
            stamp_ns = int(stamp_ns)
            fr = self._frame(stamp_ns)
            if fr is None:
                return False
            if fr.expected_axes is None:
                fr.expected_axes = list(dict.fromkeys(list(axes) + list(fr.axes)))
            for axis in fr.expected_axes:
                self._fail(fr.axes.setdefault(axis, _Group()), str(reason))
            self._check(stamp_ns)
            return True

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
                    if len(g.frames) < count:
                        parts.append(f"missing frame(s) {_missing(g.frames, count)} of {count}")
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


def _span(a: int, b: int) -> str:
    """The indices ``a .. b - 1`` as text (``"3"`` or ``"3-9"``), whatever their number."""
    return f"{a}" if b - a == 1 else f"{a}-{b - 1}"


def _missing(present: Any, count: int) -> str:
    """The indices in ``[0, count)`` not in ``present`` as runs, ``"1-3, 7"`` (at most 6 runs shown),
    computed from the indices present: never one item per missing index."""
    runs: list[str] = []
    total = 0
    start = 0
    for i in sorted(i for i in present if 0 <= i < count) + [count]:
        if i > start:
            total += 1
            if len(runs) < 6:
                runs.append(_span(start, i))
        start = i + 1
    return ", ".join(runs) + (f", ... ({count - len(present)} in all)" if total > 6 else "")


__all__ = ["AssembledFrame", "AxisSet", "PartitionAssembler"]
