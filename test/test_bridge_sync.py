"""Stamp matching, the latest-only drop policy, and partition-set assembly (pws_ros.bridge.sync)."""
from __future__ import annotations

import threading
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pws_ros.bridge.assembly import PartitionAssembler
from pws_ros.bridge.sync import LatestSlot, RateMeter, StampMatcher
from pws_ros.core.errors import PwsError

MS = 1_000_000


# ---- stamp matching ----------------------------------------------------------------------------

def test_exact_and_tolerant_matching():
    m = StampMatcher(("depth", "color", "info"), tolerance_ns=5 * MS)
    assert m.add("depth", 100 * MS, "d100") is None
    assert m.add("color", 103 * MS, "c103") is None
    got = m.add("info", 98 * MS, "i98")
    assert got is not None and got.stamp_ns == 100 * MS
    assert got.messages == {"depth": "d100", "color": "c103", "info": "i98"}
    assert got.stamps == {"depth": 100 * MS, "color": 103 * MS, "info": 98 * MS}
    assert m.matched == 1 and m.total_dropped() == 0


def test_beyond_tolerance_never_matches():
    m = StampMatcher(("depth", "color"), tolerance_ns=5 * MS)
    assert m.add("depth", 100 * MS, "d") is None
    assert m.add("color", 106 * MS, "c") is None
    assert m.pending() == {"depth": 1, "color": 1}


def test_closest_candidate_wins_and_older_ones_are_dropped():
    m = StampMatcher(("depth", "color"), tolerance_ns=10 * MS)
    for s in (90, 95, 99):
        m.add("color", s * MS, f"c{s}")
    got = m.add("depth", 100 * MS, "d100")
    assert got["color"] == "c99"
    assert m.dropped["color"] == 2  # c90, c95 can no longer be used
    assert m.pending() == {"depth": 0, "color": 0}
    # a message older than the last match is dropped on arrival
    assert m.add("color", 97 * MS, "late") is None and m.dropped["color"] == 3


def test_newest_complete_set_is_preferred():
    m = StampMatcher(("depth", "color"), tolerance_ns=1 * MS)
    m.add("depth", 100 * MS, "d100")
    m.add("depth", 133 * MS, "d133")
    got = m.add("color", 133 * MS, "c133")
    assert got["depth"] == "d133" and m.dropped["depth"] == 1


def test_buffers_are_bounded():
    m = StampMatcher(("depth", "color"), tolerance_ns=0, queue_size=3)
    for i in range(10):
        m.add("depth", i * MS, i)
    assert m.pending()["depth"] == 3 and m.dropped["depth"] == 7
    assert m.add("color", 9 * MS, "c")["depth"] == 9


def test_out_of_order_arrival_still_matches():
    m = StampMatcher(("depth", "color"), tolerance_ns=0)
    m.add("color", 200 * MS, "c200")
    m.add("color", 100 * MS, "c100")
    assert m.add("depth", 100 * MS, "d100")["color"] == "c100"
    assert m.add("depth", 200 * MS, "d200")["color"] == "c200"


def test_matcher_rejects_bad_setup():
    with pytest.raises(PwsError, match="distinct"):
        StampMatcher(("a", "a"))
    with pytest.raises(PwsError, match="tolerance"):
        StampMatcher(("a",), tolerance_ns=-1)
    with pytest.raises(PwsError, match="unknown stream 'x'"):
        StampMatcher(("a",)).add("x", 0, None)


def test_unsynced_streams_pair_as_nearest_once_settled():
    """A 6 Hz depth and a 10 Hz colour stream, unsynchronised (some pairs within 20 ms, some 26-41 ms
    apart): each depth frame pairs with its nearest colour frame, decided once later colour and depth
    frames show that no nearer one can come; pairs within the tolerance still match at once."""
    m = StampMatcher(("depth", "color"), tolerance_ns=20 * MS, max_skew_ns=200 * MS)
    depth = [40 + 167 * k for k in range(4)]          # 40, 207, 374, 541
    color = [100 * k for k in range(10)]              # 0, 100, 200, ...
    events = sorted([(t, "depth") for t in depth] + [(t, "color") for t in color])
    got = []
    for t, s in events:
        r = m.add(s, t * MS, f"{s[0]}{t}")
        if r is not None:
            got.append((r.stamps["depth"] // MS, r.stamps["color"] // MS, t))
    # the reference: each depth's nearest colour frame (all within 20 ms here but one)
    want = [(d, min(color, key=lambda c: (abs(c - d), c))) for d in depth]
    assert [(d, c) for d, c, _t in got] == want and sum(abs(d - c) > 20 for d, c in want) == 3
    for d, c, t in got:
        if abs(d - c) <= 20:
            assert t == max(d, c)                     # matched the moment its second message arrived


def test_far_pair_waits_until_settled_or_flushed():
    m = StampMatcher(("depth", "color"), tolerance_ns=20 * MS, max_skew_ns=200 * MS)
    assert m.add("color", 1000 * MS, "c") is None
    assert m.add("depth", 1100 * MS, "d1") is None    # a later colour frame could be nearer: wait
    assert m.add("depth", 1270 * MS, "d2") is None    # 270 ms: beyond the skew
    got = m.flush()                                   # the end of the recording: nothing nearer can come
    assert got is not None and got.messages == {"depth": "d1", "color": "c"}
    assert m.flush() is None
    # without max_skew the pair never forms
    m0 = StampMatcher(("depth", "color"), tolerance_ns=20 * MS)
    m0.add("color", 1000 * MS, "c")
    m0.add("depth", 1100 * MS, "d1")
    assert m0.flush() is None
    # settled by later messages on both streams: colour 1000 is d1's nearest and d1 is its nearest
    m = StampMatcher(("depth", "color"), tolerance_ns=20 * MS, max_skew_ns=200 * MS)
    m.add("color", 1000 * MS, "c")
    m.add("depth", 1100 * MS, "d1")
    assert m.add("color", 1250 * MS, "c2") is not None


def test_a_nearer_partner_on_the_reference_stream_wins():
    m = StampMatcher(("depth", "color"), tolerance_ns=20 * MS, max_skew_ns=200 * MS)
    m.add("depth", 1000 * MS, "d0")
    m.add("color", 1100 * MS, "c")                    # 100 ms from d0; a later depth may be nearer
    assert m.add("depth", 1150 * MS, "d1") is None    # 50 ms: nearer, but colour has nothing after 1150 yet
    got = m.add("color", 1300 * MS, "c2")
    assert got is not None and got.messages == {"depth": "d1", "color": "c"}


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["a", "b"]), st.integers(0, 50)), max_size=40), st.integers(0, 3), st.integers(1, 5),
       st.sampled_from([0, 2, 10]))
def test_matcher_invariants(events, tol, qsize, skew):
    """Every match is within tolerance (or the skew); matched stamps strictly increase per stream within a
    timeline (a repeated stamp, as in a looped bag, starts a new one); every message is either matched,
    dropped or still buffered; buffers never exceed the queue size."""
    m = StampMatcher(("a", "b"), tolerance_ns=tol, queue_size=qsize, max_skew_ns=skew)
    tol = max(tol, skew)
    last = {"a": -1, "b": -1}
    counts = {"a": 0, "b": 0}
    matched = 0
    jumps = 0
    for stream, stamp in events:
        counts[stream] += 1
        got = m.add(stream, stamp, (stream, stamp))
        assert max(m.pending().values()) <= qsize
        if m.time_jumps != jumps:
            assert m.time_jumps == jumps + 1 and stamp < last[stream]
            jumps, last = m.time_jumps, {"a": -1, "b": -1}
        if got is not None:
            matched += 1
            assert abs(got.stamps["a"] - got.stamps["b"]) <= tol
            for s in ("a", "b"):
                assert got.stamps[s] > last[s]
                last[s] = got.stamps[s]
    pend = m.pending()
    for s in ("a", "b"):
        assert counts[s] == matched + m.dropped[s] + pend[s]


# ---- drop policy -------------------------------------------------------------------------------

def test_latest_slot_keeps_the_newest_and_counts_drops():
    slot: LatestSlot[int] = LatestSlot()
    assert slot.put(1) is False
    assert slot.put(2) is True
    assert slot.put(3) is True
    assert slot.take(timeout=0) == 3
    assert slot.take(timeout=0.01) is None
    assert slot.stats() == {"accepted": 3, "dropped": 2, "taken": 1, "pending": 0}


def test_latest_slot_with_a_slow_worker():
    """A producer much faster than the worker: the worker sees increasing items, never a queue;
    accepted = taken + dropped (+ pending)."""
    slot: LatestSlot[int] = LatestSlot()
    seen = []
    stop = threading.Event()

    def worker():
        while not stop.is_set() or slot.peek_full():
            item = slot.take(timeout=0.05)
            if item is not None:
                seen.append(item)
                time.sleep(0.01)

    th = threading.Thread(target=worker)
    th.start()
    for i in range(200):
        slot.put(i)
        time.sleep(0.0005)
    stop.set()
    th.join(5)
    s = slot.stats()
    assert seen == sorted(seen) and len(set(seen)) == len(seen)
    assert seen[-1] == 199  # the newest input is always processed
    assert s["accepted"] == 200 and s["accepted"] == s["taken"] + s["dropped"] + s["pending"]
    assert s["dropped"] > 0 and s["taken"] == len(seen)


def test_latest_slot_close_wakes_the_worker():
    slot: LatestSlot[int] = LatestSlot()
    out = []
    th = threading.Thread(target=lambda: out.append(slot.take()))
    th.start()
    time.sleep(0.05)
    slot.close()
    th.join(2)
    assert not th.is_alive() and out == [None] and slot.closed


def test_rate_meter():
    r = RateMeter(window=5)
    assert r.rate() == 0.0
    for t in (0.0, 0.5, 1.0, 1.5, 2.0, 2.5):
        r.tick(t)
    assert r.rate() == pytest.approx(2.0)


# ---- partition assembly ------------------------------------------------------------------------

class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def feed(asm, stamp, axis, count, indices=None, bounds=True):
    for i in (range(count) if indices is None else indices):
        asm.add_frame(stamp, axis, i, count, f"{axis}{i}")
    if bounds:
        asm.add_bounds(stamp, axis, count, f"b-{axis}")


def test_complete_frame_released_in_order():
    asm = PartitionAssembler(timeout_s=5)
    asm.expect(1, {"tz": 3, "ry": 2}, info="plan")
    feed(asm, 1, "ry", 2)
    assert asm.pop_ready() == []
    feed(asm, 1, "tz", 3)
    (fr,) = asm.pop_ready()
    assert fr.complete and fr.info == "plan" and [a.axis for a in fr.axes] == ["tz", "ry"]
    assert fr.axes[0].frames == ["tz0", "tz1", "tz2"] and fr.axes[0].bounds == "b-tz"
    assert asm.pending() == [] and asm.completed == 2


def test_frames_before_the_plan_are_kept():
    asm = PartitionAssembler()
    feed(asm, 7, "tz", 2)
    assert asm.pop_ready() == []
    asm.expect(7, {"tz": 2})
    (fr,) = asm.pop_ready()
    assert fr.complete


def test_lost_frame_is_detected_at_once():
    asm = PartitionAssembler()
    asm.expect(1, {"tz": 6})
    feed(asm, 1, "tz", 6, indices=[0, 1, 3, 4, 5])
    (fr,) = asm.pop_ready()
    assert not fr.complete and fr.axes[0].frames is None
    assert fr.axes[0].error == "lost frame(s) 2 of 6 (a later frame arrived first)"


def test_duplicate_and_out_of_range_indices():
    asm = PartitionAssembler()
    asm.expect(1, {"tz": 3})
    feed(asm, 1, "tz", 3, indices=[0, 1, 1, 2])
    (fr,) = asm.pop_ready()
    assert fr.axes[0].error == "duplicate frame index 1"
    asm.expect(2, {"tz": 3})
    asm.add_frame(2, "tz", 3, 3, "x")
    (fr,) = asm.pop_ready()
    assert fr.axes[0].error == "frame index 3 out of range for 3 frames"


def test_count_disagreeing_with_the_plan():
    asm = PartitionAssembler()
    feed(asm, 1, "tz", 4, bounds=False)
    asm.expect(1, {"tz": 5})
    (fr,) = asm.pop_ready()
    assert "frame tags say 4 frames but the plan has 5" in fr.axes[0].error
    asm.expect(2, {"tz": 2})
    asm.add_frame(2, "tz", 0, 3, "x")
    (fr,) = asm.pop_ready()
    assert "says 3 frames but 2 are expected" in fr.axes[0].error


def test_timeout_releases_incomplete_sets_as_failed():
    clock = Clock()
    asm = PartitionAssembler(timeout_s=2.0, clock=clock)
    asm.expect(1, {"tz": 4, "ry": 1})
    feed(asm, 1, "tz", 4, indices=[0, 1], bounds=False)
    feed(asm, 1, "ry", 1)
    clock.t = 1.9
    assert asm.pop_ready() == []
    clock.t = 2.0
    (fr,) = asm.pop_ready()
    tz, ry = fr.axes
    assert ry.ok and not tz.ok
    assert tz.error == "incomplete partition set: missing frame(s) 2-3 of 4, no bounds arrived (timed out after 2 s)"
    # late data for a released frame is ignored
    asm.add_frame(1, "tz", 2, 4, "late")
    assert asm.pop_ready() == [] and asm.late == 1 and asm.pending() == []


def test_planner_error_axis_and_missing_bounds():
    clock = Clock()
    asm = PartitionAssembler(timeout_s=1.0, clock=clock)
    asm.expect(1, {"tz": "the plan needs 30001 partitions", "ry": 2})
    feed(asm, 1, "ry", 2, bounds=False)
    assert asm.pop_ready() == []  # waits for the bounds
    asm.add_bounds(1, "ry", 2, "b")
    (fr,) = asm.pop_ready()
    assert fr.axes[0].error == "the plan needs 30001 partitions" and fr.axes[1].ok


def test_eviction_bounds_memory():
    asm = PartitionAssembler(max_pending=2)
    for stamp in (1, 2, 3):
        asm.expect(stamp, {"tz": 2})
        asm.add_frame(stamp, "tz", 0, 2, "x")
    (fr,) = asm.pop_ready()
    assert fr.stamp_ns == 1 and "evicted" in fr.axes[0].error and "missing frame(s) 1 of 2" in fr.axes[0].error
    assert asm.pending() == [2, 3]


def test_frame_of_an_unplanned_axis():
    asm = PartitionAssembler()
    asm.expect(1, {"tz": 1})
    asm.add_frame(1, "rx", 0, 1, "x")
    feed(asm, 1, "tz", 1)
    (fr,) = asm.pop_ready()
    assert fr.complete and [a.axis for a in fr.axes] == ["tz"]


def test_without_bounds_expected():
    asm = PartitionAssembler(expect_bounds=False)
    asm.expect(1, {"tz": 2})
    feed(asm, 1, "tz", 2, bounds=False)
    (fr,) = asm.pop_ready()
    assert fr.complete and fr.axes[0].bounds is None


@settings(max_examples=60, deadline=None)
@given(count=st.integers(1, 8), drop=st.sets(st.integers(0, 7)), dup=st.booleans())
def test_assembler_never_releases_an_incomplete_set_as_complete(count, drop, dup):
    clock = Clock()
    asm = PartitionAssembler(timeout_s=1.0, clock=clock)
    asm.expect(1, {"tz": count})
    sent = [i for i in range(count) if i not in drop]
    if dup and sent:
        sent.insert(1, sent[0])
    for i in sent:
        asm.add_frame(1, "tz", i, count, i)
    asm.add_bounds(1, "tz", count, None)
    clock.t = 5.0
    (fr,) = asm.pop_ready()
    ok = not dup and len(sent) == count
    assert fr.complete == ok
    if ok:
        assert fr.axes[0].frames == list(range(count))
