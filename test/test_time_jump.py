"""Time that jumps back (a looped bag, a restarted driver, a reset clock): the matchers and the
assembler start over instead of dropping the new pass as "late" forever, and the nodes (driven
without ROS through the in-memory context of test_nodes_logic) certify both passes. Also the
shutdown guard of the publishers (ROS-free part; the rclpy glue itself needs ROS 2)."""
from __future__ import annotations

import pytest

from pws_ros.bridge import msgbuild, msgconv
from pws_ros.bridge.assembly import PartitionAssembler
from pws_ros.bridge.sync import StampMatcher
from pws_ros.nodes._common import ShutdownSafePublisher
from test_nodes_logic import T0, Bus, Context, four_nodes, params, play, wait_for

MS = 1_000_000
S = 1_000_000_000


def two_passes(n, period_ns):
    one = [T0 + k * period_ns for k in range(n)]
    return one, one + one


def test_matcher_matches_both_passes_of_a_looped_stream():
    one, stamps = two_passes(30, 100 * MS)  # a 2.9 s bag played twice
    logs = []
    m = StampMatcher(("depth", "color"), tolerance_ns=5 * MS, on_time_jump=logs.append)
    got = []
    for st in stamps:
        assert m.add("depth", st, ("d", st)) is None
        ms = m.add("color", st + 2 * MS, ("c", st))
        assert ms is not None, f"no match for stamp {st}"
        got.append(ms.stamp_ns)
    assert got == stamps and m.matched == 60 and m.total_dropped() == 0
    assert m.time_jumps == 1 and len(logs) == 1 and "jumped back by 2.902 s" in logs[0]  # from the newest match (colour, +2 ms)
    # every message is either in a match or counted as dropped
    assert 2 * m.matched + m.total_dropped() == 2 * len(stamps)


def test_small_reorder_is_not_a_jump():
    m = StampMatcher(("depth", "color"), tolerance_ns=5 * MS)
    m.add("depth", T0 + S, 1)
    assert m.add("color", T0 + S, 1) is not None
    # 0.5 s older than the last match: late, dropped and counted, no reset
    assert m.add("depth", T0 + S // 2, 2) is None and m.dropped["depth"] == 1 and m.time_jumps == 0
    # 1.5 s older: a new timeline
    m.add("depth", T0 - S // 2, 3)
    assert m.time_jumps == 1 and m.add("color", T0 - S // 2, 3) is not None
    # a jump drops (and counts) what was buffered before it
    m2 = StampMatcher(("depth", "color"), tolerance_ns=0, jump_back_tolerance_ns=S)
    m2.add("depth", T0 + 5 * S, "a")
    m2.add("color", T0 + 5 * S, "a")
    m2.add("depth", T0 + 6 * S, "pending")
    m2.add("color", T0, "new")
    assert m2.time_jumps == 1 and m2.dropped == {"depth": 1, "color": 0} and m2.pending() == {"depth": 0, "color": 1}


def feed(asm, stamp, counts):
    asm.expect(stamp, counts)
    for axis, count in counts.items():
        for i in range(count):
            asm.add_frame(stamp, axis, i, count, (axis, i))
        asm.add_bounds(stamp, axis, count, axis)


def test_assembler_assembles_both_passes():
    _, stamps = two_passes(4, 500 * MS)  # 1.5 s span
    logs = []
    asm = PartitionAssembler(on_time_jump=logs.append)
    released = []
    for st in stamps:
        feed(asm, st, {"tz": 3, "ry": 2})
        released += asm.pop_ready()
    assert [f.stamp_ns for f in released] == stamps and all(f.complete for f in released)
    assert asm.late == 0 and asm.time_jumps == 1 and len(logs) == 1


def test_assembler_fails_sets_pending_at_the_jump_and_ignores_late_data_otherwise():
    asm = PartitionAssembler()
    feed(asm, T0 + 2 * S, {"tz": 2})
    asm.expect(T0 + 3 * S, {"tz": 2})
    asm.add_frame(T0 + 3 * S, "tz", 0, 2, "x")  # incomplete when time jumps back
    assert [f.stamp_ns for f in asm.pop_ready()] == [T0 + 2 * S]
    asm.add_bounds(T0 + 2 * S, "tz", 2, "late")  # a released stamp 1 s back (not more): late
    assert asm.late == 1 and asm.time_jumps == 0
    feed(asm, T0, {"tz": 2})  # 3 s back: a new pass
    out = asm.pop_ready()
    assert asm.time_jumps == 1
    failed = [f for f in out if f.stamp_ns == T0 + 3 * S]
    assert failed and not failed[0].complete and "time jumped back by 3.000 s" in failed[0].axes[0].error
    assert [f.stamp_ns for f in out if f.complete] == [T0]


@pytest.mark.parametrize("n", [2, 8])
def test_a_loop_shorter_than_the_tolerance_is_a_jump(n):
    """The shipped demo bag spans 0.7 s (8 frames at 10 Hz): its loop jumps back by less than the 1 s
    tolerance, but repeats stamps already matched / planned, which a live stream never does. (A one-frame
    loop repeats only the last stamp: a duplicate, dropped.)"""
    _, stamps = two_passes(n, 100 * MS)
    logs = []
    m = StampMatcher(("depth", "color"), tolerance_ns=5 * MS, on_time_jump=logs.append)
    asm = PartitionAssembler(on_time_jump=logs.append)
    got, released = [], []
    for st in stamps:
        m.add("color", st, st)
        ms = m.add("depth", st, st)
        got.append(ms.stamp_ns if ms is not None else None)
        feed(asm, st, {"tz": 2})
        released += asm.pop_ready()
    assert got == stamps and m.time_jumps == 1 and m.total_dropped() == 0
    assert [f.stamp_ns for f in released] == stamps and all(f.complete for f in released)
    assert asm.time_jumps == 1 and asm.late == 0 and len(logs) == 2
    # a late message of a matched stamp that is not a repeat in a new order stays late
    assert m.add("depth", stamps[-1], "dup") is None and m.time_jumps == 1
    asm.add_bounds(stamps[-1], "tz", 2, "late")  # late data (not a plan) for a released stamp
    assert asm.late == 1 and asm.time_jumps == 1


@pytest.fixture
def model_path(make_model_file):
    return make_model_file(input_size=(24, 32))


def stamps_of(msgs):
    return [msgconv.stamp_to_ns(m.header.stamp) for m in msgs]


@pytest.mark.parametrize("period", [600 * MS, 100 * MS])  # the loop jumps back 1.2 s / 0.2 s (< the tolerance)
def test_pipeline_certifies_both_passes_of_a_looped_bag(model_path, period):
    from pws_ros.nodes.pipeline import PipelineNode

    _, stamps = two_passes(3, period)
    bus = Bus()
    ctx = Context(bus, "pipeline", **params(model_path))
    node = PipelineNode(ctx)
    try:
        play(bus, stamps, lambda: bus.published["/certification"])
        certs = bus.published["/certification"]
        assert stamps_of(certs) == stamps
        assert all(v["level"] in (0, 1) for m in certs for v in msgbuild.parse_certification(m).values())
        warns = [m for lvl, m in ctx.logs if lvl == "warn" and "time jumped back" in m]
        assert len(warns) == 1
        assert wait_for(lambda: node.worker.processed == 6 and not node.worker.busy)
        c = node._counters()
        assert c["frames_processed"] == 6 and c["frames_dropped"] == 0 and c["extra"]["time_jumps_back"] == 1
    finally:
        node.close()
        bus.close()
    assert not bus.errors, bus.errors


@pytest.mark.parametrize("period", [1200 * MS, 100 * MS])
def test_four_processes_certify_both_passes_of_a_looped_bag(model_path, period):
    _, stamps = two_passes(2, period)
    bus = Bus()
    ctxs, nodes = four_nodes(bus, model_path)
    try:
        play(bus, stamps, lambda: bus.published["/certification"], tick=[ctxs["certifier"]])
        certs = bus.published["/certification"]
        assert stamps_of(certs) == stamps
        assert all(v["level"] in (0, 1) for m in certs for v in msgbuild.parse_certification(m).values())
        for name in ("cloud_listener", "partition_planner", "certifier"):
            assert len([m for lvl, m in ctxs[name].logs if lvl == "warn" and "time jumped back" in m]) == 1, name
        cert = nodes[3]
        assert cert.assembler.time_jumps == 1 and cert.assembler.late == 0
    finally:
        for nd in nodes:
            nd.close()
        bus.close()
    assert not bus.errors, bus.errors


def test_pose_publishers_exist_before_any_frame(model_path):
    from pws_ros.nodes.pipeline import PipelineNode

    bus = Bus()
    ctx = Context(bus, "pipeline", **params(model_path))
    node = PipelineNode(ctx)
    try:  # created up front, never by the worker (which may run after shutdown began)
        assert "/plan/poses/tx" in ctx.qos and "/plan/poses/tz" in ctx.qos
    finally:
        node.close()
        bus.close()


class _Pub:
    def __init__(self, fail_with=None):
        self.sent, self.fail_with = [], fail_with

    def publish(self, msg):
        if self.fail_with is not None:
            raise self.fail_with
        self.sent.append(msg)


def test_publishing_after_shutdown_is_skipped_silently():
    state = {"ok": True}
    raw = _Pub()
    pub = ShutdownSafePublisher(raw, lambda: state["ok"])
    pub.publish(1)
    state["ok"] = False
    pub.publish(2)
    assert raw.sent == [1] and pub.skipped == 1
    # a publish racing with the shutdown: the failure is swallowed only once the context is down
    answers = iter([True, False])  # up before the publish, down when it failed
    racing = ShutdownSafePublisher(_Pub(RuntimeError("publisher's context is invalid")), lambda: next(answers))
    racing.publish(3)
    assert racing.skipped == 1
    racing.ok = lambda: True  # a failure while the context is up is not hidden
    with pytest.raises(RuntimeError):
        racing.publish(4)


def test_a_frame_failing_during_shutdown_is_not_logged_as_an_error():
    import threading

    from pws_ros.nodes._common import Worker

    logs, started, release = [], threading.Event(), threading.Event()

    def fn(item):
        started.set()
        release.wait(5)
        raise RuntimeError("publisher's context is invalid")

    w = Worker("t", fn, lambda level, msg: logs.append((level, msg)))
    w.submit(1)
    assert started.wait(5)
    w.close(timeout=0)  # shutdown begins while the frame is in flight
    release.set()
    w.thread.join(5)
    assert [lvl for lvl, _m in logs] == ["info"] and "abandoned at shutdown" in logs[0][1]
    # the same failure while running is an error
    logs.clear()
    w2 = Worker("t2", lambda item: (_ for _ in ()).throw(RuntimeError("boom")), lambda level, msg: logs.append((level, msg)))
    w2.submit(1)
    assert wait_for(lambda: logs, timeout=5)
    w2.close()
    assert logs[0][0] == "error" and "boom" in logs[0][1]
