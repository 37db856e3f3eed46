"""Issue 35: what a robot stack consumes: the ``certified_label`` topic (only frames certified on every
axis, with one label), the health status' WARN when no frame has been certified for longer than
``certified_label_timeout_s``, and the ``certification/overlay`` image (``publish_overlay``) of the
pipeline and the four-process certifier. rclpy-free: the nodes run on the in-memory context of
test_nodes_logic (rosbags messages after a CDR round trip); the live check is test_live_outputs.py."""
from __future__ import annotations

import numpy as np
import pytest

from pws_ros.bridge import msgbuild, msgconv, outputs
from pws_ros.core.result import Certificate, error_certificate
from test_nodes_logic import T, T0, Bus, Context, bus, four_nodes, params, play, wait_for  # noqa: F401 (bus: a fixture)

STAMP = 1_700_000_000_123_456_789


def cert(axis="tz", status="certified", label=3, radius=None, requested=0.01, p_a=(0.9, 0.95)):
    certified = status == "certified"
    return Certificate(axis=axis, unit="m" if axis[0] == "t" else "rad", method="pws_of", coverage="anchors",
                       requested_radius=requested, status=status, certified=certified,
                       radius=requested if radius is None else radius, label=label, class_name=f"class{label}",
                       p_a_lower=list(p_a), frame_alpha=0.01)


def every_axis_certified(certification) -> bool:
    """The reference, from the ``certification`` message alone: every status OK, certified, and one label."""
    statuses = [{kv.key: kv.value for kv in st.values} | {"level": msgbuild.level_to_int(st.level)} for st in certification.status]
    return (bool(statuses) and all(s["level"] == 0 and s["certified"] == "true" for s in statuses)
            and len({s["label"] for s in statuses}) == 1)


@pytest.mark.parametrize("certs,expected", [
    ([cert("tz"), cert("ry", requested=0.0044)], True),
    ([cert("tz")], True),
    ([cert("tz"), cert("ry", status="not_certified", radius=0.002, requested=0.0044)], False),
    ([cert("tz"), cert("ry", status="abstain", label=-1, radius=0.0)], False),
    ([cert("tz"), error_certificate("ry", "rad", "pws_of", "anchors", 0.0044, "lost frame")], False),
    ([cert("tz", label=3), cert("ry", label=4, requested=0.0044)], False),   # the axes certified different labels
    ([], False),
])
def test_certified_label_only_for_frames_certified_on_every_axis(certs, expected):
    header = msgbuild.make_header(T, STAMP, "cam")
    msg = msgbuild.certified_label_array(header, certs, node_name="n", types=T)
    assert (msg is not None) is expected
    if msg is None:
        return
    assert msg.header.stamp == header.stamp and msg.header.frame_id == "cam"
    (st,) = msg.status
    assert st.name == "pws/certified_label" and msgbuild.level_to_int(st.level) == 0 and st.message == "class3"
    assert st.hardware_id == "cam"
    values = {kv.key: kv.value for kv in st.values}
    assert [kv.key for kv in st.values] == (["label", "class_name", "p_a_lower", "frame_alpha", "axes"]
                                            + [f"radius.{c.axis}" for c in certs] + ["node"])
    assert values["label"] == "3" and values["class_name"] == "class3" and values["axes"] == ",".join(c.axis for c in certs)
    assert float(values["p_a_lower"]) == 0.9 and float(values["frame_alpha"]) == 0.01
    for c in certs:
        assert float(values[f"radius.{c.axis}"]) == c.radius


def test_the_label_goes_out_before_the_certification_in_every_path(make_model_file):
    """The pipeline node, the four-process certifier and replay put the label at the same place: after the
    markers, before the certification (which stays last)."""
    from test_outputs import RecordingContext, _replay_sent
    from pws_ros.bridge.engine import FrameResult
    from pws_ros.bridge.inputs import RawFrame
    from pws_ros.nodes.certifier import CertifierNode
    from pws_ros.nodes.pipeline import PipelineNode

    certs = [cert("tx", requested=0.05), cert("tz")]
    result = FrameResult(STAMP, "cam", certs, {}, None, {"tx": 0.1, "tz": 0.1, "total": 0.2})
    replay = [(t.lstrip("/"), m) for t, m in _replay_sent(certs, result.compute_ms, None, result)]
    assert [t for t, _ in replay] == ["certification/markers", "certified_label", "certification"]
    model = str(make_model_file(input_size=(24, 32)))
    ctx = RecordingContext("pipeline", model_path=model, axes=["tx", "tz"])
    node = PipelineNode(ctx)
    try:
        node._publish(RawFrame("rgbd", STAMP, msgbuild.make_header(T, STAMP, "cam")), certs, compute_ms=result.compute_ms,
                      result=result)
    finally:
        node.close()
    ctx4 = RecordingContext("certifier", model_path=model, axes=["tx", "tz"])
    node4 = CertifierNode(ctx4)
    try:
        node4._publish(result, ctx4.config)
    finally:
        node4.close()
    for sent in (ctx.sent, ctx4.sent):
        assert [t for t, _ in sent] == [t for t, _ in replay]
        label = dict(sent)["certified_label"]
        assert [(kv.key, kv.value) for kv in label.status[0].values][:-1] == [
            (kv.key, kv.value) for kv in dict(replay)["certified_label"].status[0].values][:-1]   # all but the node name


def test_the_watch_warns_past_the_timeout():
    now = [100.0]
    watch = outputs.CertifiedLabelWatch(clock=lambda: now[0])
    assert watch.warning(5.0) == "" and np.isnan(watch.age_s())        # no frame yet: nothing to say
    watch.saw([("certification", None)])
    now[0] = 104.0
    assert watch.warning(5.0) == ""
    now[0] = 106.0
    assert watch.warning(5.0) == ("no frame certified on every axis in the 6.0 s since the first frame "
                                  "(certified_label_timeout_s 5)")
    assert watch.warning(0.0) == ""                                    # 0: never
    watch.saw([("certified_label", None), ("certification", None)])
    now[0] = 110.0
    assert watch.warning(5.0) == "" and watch.counters() == {"certified_labels": 1, "since_certified_label_s": 4.0}
    watch.saw([("certification", None)])                               # a frame not certified: the clock goes on
    now[0] = 111.5
    assert watch.warning(5.0) == "no frame certified on every axis for 5.5 s (certified_label_timeout_s 5)"


def _health(bus, ctx):
    ctx.tick()
    assert wait_for(bus.idle)
    return msgbuild.diagnostic_array_to_dicts(bus.published["/diagnostics"][-1])[0]


def _check_overlays(bus, certs):
    """Every overlay image has the stamp and frame id of a certification; its size is the layout's."""
    stamps = {msgconv.stamp_to_ns(m.header.stamp) for m in certs}
    overlays = bus.published["/certification/overlay"]
    assert overlays
    for img in overlays:
        assert msgconv.stamp_to_ns(img.header.stamp) in stamps and img.header.frame_id == "cam"
        # a 32x24 view scaled up 20x (to 640 px), a 34 px header and a 28 px row per axis
        assert (img.encoding, img.width, img.height) == ("rgb8", 640, 24 * 20 + 34 + 2 * 28)
    return overlays


def test_pipeline_publishes_the_certified_labels_overlays_and_warns(bus, model_path):
    from pws_ros.nodes.pipeline import PipelineNode

    # the second frame's tz radius cannot be certified at ±0.5 m: only the first frame is certified on every axis
    ctx = Context(bus, "pipeline", **params(model_path, publish_overlay=True, certified_label_timeout_s=5.0,
                                            certification_to_diagnostics=True, **{"radius.tx": 0.001, "radius.tz": 0.002}))
    node = PipelineNode(ctx)
    now = [0.0]
    node.health.labels.clock = lambda: now[0]
    try:
        play(bus, [T0], lambda: bus.published["/certification"])
        ctx.config = ctx.config.with_params({"radius.tz": 0.5})
        node._on_change(ctx.config)
        play(bus, [T0 + 100_000_000], lambda: bus.published["/certification"][1:])
        certs = bus.published["/certification"]
        assert wait_for(lambda: node.overlay.worker.processed + node.overlay.worker.slot.dropped == 2 and not node.overlay.worker.busy)
        labelled = [msgconv.stamp_to_ns(m.header.stamp) for m in bus.published["/certified_label"]]
        assert labelled == [msgconv.stamp_to_ns(m.header.stamp) for m in certs if every_axis_certified(m)] == [T0]
        assert bus.published["/certified_label"][0].status[0].message == "c1"
        _check_overlays(bus, certs)
        # certification_to_diagnostics: each certification also on /diagnostics (for diagnostic_aggregator)
        forwarded = [m for m in bus.published["/diagnostics"] if m.status[0].name.startswith("pws/")]
        assert [msgbuild.parse_certification(m) for m in forwarded] == [msgbuild.parse_certification(m) for m in certs]
        h = _health(bus, ctx)
        assert h["level"] == 0 and h["values"]["certified_labels"] == "1"
        assert int(h["values"]["overlays_published"]) + int(h["values"]["overlays_skipped"]) == 2
        now[0] = 7.0     # 7 s (on the watch's clock) after the last certified label
        h = _health(bus, ctx)
        assert h["level"] == 1 and h["message"] == "no frame certified on every axis for 7.0 s (certified_label_timeout_s 5)"
    finally:
        node.close()


def test_no_overlay_when_off(bus, model_path):
    from pws_ros.nodes.pipeline import PipelineNode

    ctx = Context(bus, "pipeline", **params(model_path))
    node = PipelineNode(ctx)
    try:
        assert node.overlay.worker is None           # no thread, no publisher
        play(bus, [T0], lambda: bus.published["/certification"])
        assert "/certification/overlay" not in bus.published and "overlays_published" not in _health(bus, ctx)["values"]
    finally:
        node.close()


def test_four_processes_publish_the_certified_labels_and_overlays(bus, model_path):
    stamps = [T0 + k * 100_000_000 for k in range(2)]
    ctxs, nodes = four_nodes(bus, model_path, publish_overlay=True, **{"radius.tx": 0.001, "radius.tz": 0.002})
    try:
        play(bus, stamps, lambda: bus.published["/certification"], tick=[ctxs["certifier"]])
        certs = bus.published["/certification"]
        cert_node = nodes[-1]
        assert wait_for(lambda: cert_node.overlay.worker.processed + cert_node.overlay.worker.slot.dropped == 2
                        and not cert_node.overlay.worker.busy)
        labelled = [msgconv.stamp_to_ns(m.header.stamp) for m in bus.published["/certified_label"]]
        assert labelled == [msgconv.stamp_to_ns(m.header.stamp) for m in certs if every_axis_certified(m)] == stamps
        for img in _check_overlays(bus, certs):   # the view is the plan's α = 0 frame, not a blank one
            pixels = np.frombuffer(bytes(img.data), np.uint8).reshape(img.height, img.width, 3)[: 24 * 20]
            assert pixels.std() > 5
    finally:
        for nd in nodes:
            nd.close()


@pytest.fixture
def model_path(make_model_file):
    return make_model_file(input_size=(24, 32))


def test_the_aggregator_file_groups_the_statuses_the_nodes_publish():
    """config/diagnostic_aggregator.yaml, with GenericAnalyzer's matching rules written out
    (diagnostic_aggregator/src/generic_analyzer.cpp: ``startswith`` = a prefix, ``regex`` = std::regex_match):
    the certification statuses go to PWS/Certification, every node's health to PWS/Nodes, nothing to both."""
    import re
    from pathlib import Path

    import yaml

    cfg = yaml.safe_load((Path(__file__).resolve().parents[1] / "config" / "diagnostic_aggregator.yaml").read_text())
    group = cfg["analyzers"]["ros__parameters"]["pws"]
    assert group["type"] == "diagnostic_aggregator/AnalyzerGroup" and group["path"] == "PWS"
    cert_rule, health_rule = group["analyzers"]["certification"], group["analyzers"]["health"]
    assert cert_rule["type"] == health_rule["type"] == "diagnostic_aggregator/GenericAnalyzer"

    def in_certification(name):
        return any(name.startswith(s) for s in cert_rule["startswith"])

    def in_nodes(name):
        return any(re.fullmatch(r, name) for r in health_rule["regex"])

    header = msgbuild.make_header(T, STAMP, "cam")
    certification = msgbuild.certificates_to_diagnostic_array(header, [cert(a) for a in ("tx", "ty", "tz", "rx", "ry", "rz")],
                                                              node_name="pipeline", types=T, latency_ms=1.0)
    for st in certification.status:
        assert in_certification(st.name) and not in_nodes(st.name)
    for node in ("pipeline", "pipeline_0", "pipeline_11", "cloud_listener", "partition_planner", "projector", "certifier"):
        (st,) = msgbuild.health_status(header, node_name=node, types=T, rate_hz=1.0, frames_in=1, frames_processed=1,
                                       frames_dropped=0, device="cpu").status
        assert in_nodes(st.name) and not in_certification(st.name)
    assert not in_nodes("camera_driver: health") and not in_certification("/camera/temperature")
