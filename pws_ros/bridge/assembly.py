"""Partition-set assembly (four-process mode, thread-safe, ROS-free).

:class:`PartitionAssembler` collects the rendered frames and bounds of each ``(stamp, axis)`` by
index against the expected count; a lost (gap), duplicate or out-of-range index, a count that
disagrees with the plan, or a timeout makes the set *failed*: an incomplete partition set is never
certified. A stamp that jumps back starts a new timeline (:mod:`pws_ros.bridge.timejump`).
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
                 on_time_jump: Callable[[str], None] | None = None):
        require(timeout_s > 0, f"assembly timeout must be positive, got {timeout_s}")
        require(int(max_pending) >= 1, f"max_pending must be >= 1, got {max_pending}")
        self.timeout_s = float(timeout_s)
        self.max_pending = int(max_pending)
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
            g = self._group(stamp_ns, axis)
            if g is None:
                return
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
            g = self._group(stamp_ns, axis)
            if g is None:
                return
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


__all__ = ["AssembledFrame", "AxisSet", "PartitionAssembler"]
