"""One frame, three code paths: ``pws replay``'s bag writer, the ``pipeline`` node and the four-process
``certifier`` node publish the same topics, the same certification keys, in the same order
(:mod:`pws_ros.bridge.outputs`). rclpy-free: the nodes run on a recording context (the interface of
``pws_ros.nodes._ros.NodeContext``) with rosbags messages; the rclpy glue itself is tested where ROS 2 exists."""
from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest

from pws_ros.bridge import msgbuild
from pws_ros.bridge.config import config_from_params
from pws_ros.bridge.engine import FrameResult
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import Cloud
from pws_ros.core.result import Certificate, error_certificate

T = msgbuild.rosbags_types()
STAMP = 1_700_000_000_123_456_789
CAM = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5, "cam")
# the documented key schema (docs/ros2.md), written out here independently of msgbuild's tuples
KEYS = ["label", "class_name", "certified", "radius", "unit", "p_a_lower", "sigma", "n", "alpha", "frame_alpha",
        "num_partitions", "classifier_calls", "latency_ms", "compute_ms", "status", "requested_radius", "method",
        "coverage", "n0", "delta_alpha", "num_bounds", "frames_rendered", "imaging", "filled_points", "working_volume",
        "reason", "node"]
# the documented order (docs/ros2.md, Outputs): the certification last
PIPELINE_TOPICS = ["cloud", "cloud/camera_info", "plan/poses/tx", "plan/poses/tz", "rendered/preview", "rendered/preview",
                   "certification/markers", "certification"]


def _result() -> tuple[FrameResult, SimpleNamespace]:
    certs = [Certificate(axis="tx", unit="m", method="pws_of", coverage="anchors", requested_radius=0.05, status="certified",
                         certified=True, radius=0.05, label=1, class_name="b", p_a_lower=[0.9, 0.95], sigma=0.5, n0=16, n=32,
                         num_bounds=2, num_partitions=5, classifier_calls=80),
             error_certificate("tz", "m", "pws_of", "anchors", 0.01, "projector: lost frame 3")]
    plans = {"tx": SimpleNamespace(axis="tx", alphas=np.linspace(-0.05, 0.05, 5)),
             "tz": SimpleNamespace(axis="tz", alphas=np.linspace(-0.01, 0.01, 3))}
    previews = [("tx", 0, np.zeros((24, 32, 3), np.uint8)), ("tx", 2, np.full((24, 32, 3), 200, np.uint8))]
    result = FrameResult(STAMP, "cam", certs, plans, CAM, {"tx": 0.5, "tz": 0.01, "total": 0.51}, previews)
    pts = np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 1.2]])
    frame = SimpleNamespace(cloud=Cloud(pts, np.full((2, 3), 0.5)), intrinsics=CAM)
    return result, frame


class RecordingContext:
    """The NodeContext interface; every publish is recorded, in order, as (topic, message)."""

    def __init__(self, name, **params):
        self.name, self.types = name, T
        self.config = config_from_params(params)
        self.on_change = None
        self.qos_events = 0
        self.sent: list[tuple[str, object]] = []

    def log(self, level, message):
        pass

    def now_ns(self):
        return time.time_ns()

    def resolve(self, topic):
        return topic

    def publisher(self, msg_type, topic, *, kind=None, depth=None):
        sent = self.sent

        class Pub:
            def publish(self, msg):
                assert type(msg) is msg_type, (topic, type(msg), msg_type)
                sent.append((topic, msg))

        return Pub()

    def subscription(self, msg_type, topic, callback, *, kind=None, depth=None):
        pass

    def timer(self, period, callback):
        return callback


def _keys(diag):
    return [[kv.key for kv in st.values] for st in diag.status]


def _check_certification(msg, node):
    assert [st.name for st in msg.status] == ["pws/tx", "pws/tz"]
    assert _keys(msg) == [KEYS, KEYS]
    parsed = msgbuild.parse_certification(msg)
    assert parsed["tx"]["certified"] is True and parsed["tz"]["status"] == "error" and parsed["tz"]["node"] == node
    assert msgbuild.level_to_int(msg.status[1].level) == 2 and "lost frame 3" in msg.status[1].message


def _check_same(sent_a, sent_b):
    """Same topics, same order, same header, same certification keys and values (latency aside)."""
    assert [t for t, _ in sent_a] == [t for t, _ in sent_b]
    for (t, a), (_, b) in zip(sent_a, sent_b):
        assert type(a).__msgtype__ == type(b).__msgtype__
        if t == "certification":
            assert _keys(a) == _keys(b)
            for sa, sb in zip(a.status, b.status):
                va = {kv.key: kv.value for kv in sa.values if kv.key not in ("latency_ms", "node")}
                vb = {kv.key: kv.value for kv in sb.values if kv.key not in ("latency_ms", "node")}
                assert va == vb


def _replay_sent(certs, compute_ms, frame, result, **opts):
    from pws_ros.replay import Replay, ReplayOptions

    written = []

    class Writer:
        def write(self, topic, msg, stamp_ns):
            assert stamp_ns == STAMP
            written.append((topic, msg))

        def flush(self):
            pass

    rep = Replay(ReplayOptions(bag="unused", **opts))
    rep.config, rep.types, rep.writer = rep.opts.config, T, Writer()
    header = msgbuild.make_header(T, STAMP, "cam")
    rep._emit(header, certs, STAMP, latency_ms=12.0, compute_ms=compute_ms, frame=frame, result=result)
    rep._commit()  # a frame's messages are written together once it is done
    return written


@pytest.fixture
def model_path(make_model_file):
    return make_model_file(input_size=(24, 32))


def test_the_three_paths_publish_the_same_frame_alike(model_path):
    from pws_ros.bridge.inputs import RawFrame
    from pws_ros.nodes.certifier import CertifierNode
    from pws_ros.nodes.pipeline import PipelineNode

    result, frame = _result()
    # replay, with the outputs the pipeline node publishes by default plus cloud and preview
    replay = _replay_sent(result.certificates, result.compute_ms, frame, result, write_cloud=True, preview=True, namespace="")
    replay = [(t.lstrip("/"), m) for t, m in replay]
    assert [t for t, _ in replay] == PIPELINE_TOPICS
    _check_certification(replay[-1][1], "pws_replay")

    # the pipeline node (in-process mode)
    ctx = RecordingContext("pipeline", model_path=str(model_path), axes=["tx", "tz"], publish_cloud=True, publish_preview=True)
    node = PipelineNode(ctx)
    try:
        raw = RawFrame("rgbd", STAMP, msgbuild.make_header(T, STAMP, "cam"))
        node._publish(raw, result.certificates, compute_ms=result.compute_ms, frame=frame, result=result)
    finally:
        node.close()
    _check_same(ctx.sent, replay)
    _check_certification(ctx.sent[-1][1], "pipeline")

    # the four-process certifier: markers and certification only, the same as the others' last two
    ctx4 = RecordingContext("certifier", model_path=str(model_path), axes=["tx", "tz"], publish_cloud=True, publish_preview=True)
    node4 = CertifierNode(ctx4)
    try:
        node4._publish(result, ctx4.config)
    finally:
        node4.close()
    assert [t for t, _ in ctx4.sent] == ["certification/markers", "certification"]
    _check_same(ctx4.sent, replay[-2:])
    _check_certification(ctx4.sent[-1][1], "certifier")


def test_an_unreadable_input_publishes_its_certification_only(model_path):
    """The input-error path: no cloud, no markers, no poses; replay writes what the node publishes."""
    from pws_ros.bridge.inputs import RawFrame
    from pws_ros.nodes.pipeline import PipelineNode

    certs = [error_certificate(a, "m", "pws_of", "anchors", 0.01, "input: depth and colour are not registered") for a in ("tx", "tz")]
    replay = _replay_sent(certs, 0.0, None, None, write_cloud=True, preview=True)
    ctx = RecordingContext("pipeline", model_path=str(model_path), axes=["tx", "tz"], publish_cloud=True)
    node = PipelineNode(ctx)
    try:
        node._publish(RawFrame("rgbd", STAMP, msgbuild.make_header(T, STAMP, "cam")), certs, compute_ms=0.0)
    finally:
        node.close()
    assert [t for t, _ in ctx.sent] == ["certification"] == [t.lstrip("/") for t, _ in replay]
    assert _keys(ctx.sent[0][1]) == [KEYS, KEYS]


def test_switches_leave_out_what_is_off():
    from pws_ros.bridge import outputs

    result, frame = _result()
    header = msgbuild.make_header(T, STAMP, "cam")
    topics = lambda sw, **kw: [t for t, _ in outputs.frame_outputs(  # noqa: E731
        T, header, result.certificates, node_name="n", latency_ms=1.0, compute_ms=None, switches=sw, **kw)]
    off = outputs.OutputSwitches(cloud=False, markers=False, poses=False, preview=False)
    assert topics(off, frame=frame, result=result) == ["certification"]
    assert topics(outputs.OutputSwitches(), frame=frame, result=result) == [
        "plan/poses/tx", "plan/poses/tz", "certification/markers", "certification"]
    # a converted frame without a result (e.g. method pws without its dense cloud): cloud, markers, certification
    assert topics(outputs.OutputSwitches(cloud=True, preview=True), frame=frame) == [
        "cloud", "cloud/camera_info", "certification/markers", "certification"]
    assert outputs.frame_error(result.certificates) == ""
    assert outputs.frame_error(result.certificates[1:]) == "projector: lost frame 3"
    assert outputs.summary_line(STAMP, result.certificates).startswith(f"frame {STAMP}: pws_of/anchors tx")


def test_replay_writes_every_frame_in_the_published_order(tmp_path, monkeypatch, make_model_file):
    """End to end through ``Replay.process``: the result bag receives each frame's messages in the order above."""
    from pws_ros import replay as rp
    from pws_ros.replay import run as replay_run
    from pws_ros.sim.record import record

    bag = record(tmp_path / "sim", frames=2, width=32, height=24, views_per_scene=1)
    written = []

    class RecordingWriter(replay_run.BagWriter):
        def write(self, topic, msg, log_time_ns, msgtype=None):
            written.append((log_time_ns, topic))
            return super().write(topic, msg, log_time_ns, msgtype)

    monkeypatch.setattr(replay_run, "BagWriter", RecordingWriter)
    cfg = config_from_params({"model_path": str(make_model_file(input_size=(24, 32))), "axes": ["tx", "tz"], "radius.tx": 0.002,
                              "radius.tz": 0.002, "n0": 16, "n": 32, "preview_every": 8})
    res = rp.replay(rp.ReplayOptions(bag=bag, config=cfg, out=tmp_path / "out", write_cloud=True, preview=True, quiet=True))
    assert len(res.records) == 2
    stamps = sorted({t for t, _ in written})
    assert [r.stamp_ns for r in res.records] == stamps
    for stamp in stamps:
        topics = [topic.lstrip("/") for t, topic in written if t == stamp]
        k = topics.count("rendered/preview")
        assert k >= 2  # every 8th frame and the alpha = 0 frame
        rec = next(r for r in res.records if r.stamp_ns == stamp)
        every_axis = all(c.status == "certified" for c in rec.certificates) and len({c.label for c in rec.certificates}) == 1
        label = ["certified_label"] if every_axis else []   # before the certification, for a frame certified on every axis
        assert topics == PIPELINE_TOPICS[:4] + ["rendered/preview"] * k + PIPELINE_TOPICS[-2:-1] + label + PIPELINE_TOPICS[-1:], topics
