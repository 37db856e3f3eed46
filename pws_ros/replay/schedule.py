"""Input messages in header-stamp order, and the live node's online policy on recorded time."""
from __future__ import annotations

import bisect
import heapq
import math
from collections import Counter
from typing import Any, Callable

from ..bagio import BagMessage, BagReader
from ..bridge import msgconv
from ..bridge.sync import LatestSlot
from ..core.errors import PwsError


class RealtimeScheduler:
    """The live node's online policy on recorded time: one worker and the live node's one-item mailbox
    (:class:`~pws_ros.bridge.sync.LatestSlot`, the same drop rule and counters).

    ``arrive(item, t)``: the worker, if free at ``t``, starts on ``item`` at once; if busy, ``item``
    waits in the slot, replacing (dropping) an older waiting item. ``process(item, start)`` runs an
    item and returns how long it took (seconds); the worker is busy until ``start + duration``.
    """

    def __init__(self, process: Callable[[Any, float], float], on_drop: Callable[[Any], None] | None = None):
        self.process = process
        self.on_drop = on_drop
        self.t_free = -math.inf
        self.slot: LatestSlot[tuple[Any, float]] = LatestSlot()
        self.processed = 0

    @property
    def dropped(self) -> int:
        return self.slot.dropped

    def _run(self, item: Any, start: float) -> None:
        self.processed += 1
        self.t_free = start + max(0.0, float(self.process(item, start)))

    def _run_waiting(self) -> None:
        item, t0 = self.slot.take(timeout=0)
        self._run(item, max(self.t_free, t0))

    def arrive(self, item: Any, t: float) -> None:
        if self.slot.peek_full() and self.t_free <= t:
            self._run_waiting()
        if self.t_free <= t and not self.slot.peek_full():
            self._run(item, t)
            return
        dropped, old = self.slot.replace((item, t))
        if dropped and self.on_drop is not None:
            self.on_drop(old[0])

    def finish(self) -> None:
        if self.slot.peek_full():
            self._run_waiting()


def _stamp_of(msg: Any, log_time: int) -> int:
    header = getattr(msg, "header", None)
    if header is not None and getattr(header, "stamp", None) is not None:
        return msgconv.header_stamp_ns(msg)
    return int(log_time)


def stamp_ordered(bag: BagReader, roles: dict[str, str], warn: Callable[[str], None], *, window_ns: int = 500_000_000,
                  cap: int = 64, copy: Callable[[BagMessage], None] | None = None):
    """``(role, BagMessage, decoded, stamp_ns)`` of the input topics in header-stamp order.

    A bounded reorder buffer (stamps older than the newest seen minus ``window_ns`` or more than
    ``cap`` messages are released) sorts by (stamp, role priority, log time): at equal stamps
    CameraInfo goes before images, so a frame finds its CameraInfo. Undecodable messages are
    skipped with one warning per topic.
    """
    prio = {"truth": 0, "info": 1, "depth_info": 1, "color": 2, "depth": 3, "points": 4}
    by_topic: dict[str, list[str]] = {}
    for role, t in roles.items():
        by_topic.setdefault(t, []).append(role)
    heap: list[tuple] = []
    newest = -(2**63)
    seq = 0
    bad: Counter = Counter()
    for m in bag.messages(by_topic):
        if copy is not None:
            copy(m)
        try:
            msg = bag.deserialize(m)
        except PwsError as exc:
            bad[m.topic] += 1
            if bad[m.topic] == 1:
                warn(f"skipping undecodable message(s) on {m.topic}: {exc}")
            continue
        stamp = _stamp_of(msg, m.log_time_ns)
        for role in by_topic[m.topic]:
            heapq.heappush(heap, (stamp, prio.get(role, 9), m.log_time_ns, seq, role, m, msg))
            seq += 1
        newest = max(newest, stamp)
        while heap and (len(heap) > cap or heap[0][0] < newest - window_ns):
            item = heapq.heappop(heap)
            yield item[4], item[5], item[6], item[0]
    while heap:
        item = heapq.heappop(heap)
        yield item[4], item[5], item[6], item[0]


def closest_gap_ms(a: list[int], b: list[int]) -> float | None:
    if not a or not b:
        return None
    b = sorted(b)
    best = math.inf
    for x in a:
        i = bisect.bisect_left(b, x)
        for j in (i - 1, i):
            if 0 <= j < len(b):
                best = min(best, abs(b[j] - x))
    return best / 1e6

