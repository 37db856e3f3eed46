"""The node classes driven without ROS: each gets an in-memory context (the interface of
``pws_ros.nodes._ros.NodeContext``) whose topics deliver rosbags messages after a CDR round trip,
one callback at a time from a dispatcher thread (like a single-threaded executor). This is not a
stand-in for rclpy: the rclpy glue itself is exercised by test_nodes_rclpy.py where ROS 2 exists."""
from __future__ import annotations

import queue
import threading
import time
from collections import defaultdict

import numpy as np
import pytest

from pws_ros.bridge import cloudconv, msgbuild, msgconv, scheme
from pws_ros.bridge.config import config_from_params
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.nodes._common import TF_MESSAGE_TYPE

T = msgbuild.rosbags_types()
TS = T.typestore
T.TFMessage = TS.types[TF_MESSAGE_TYPE]  # as pws_ros.nodes._ros.rclpy_types gives it
T0 = 1_700_000_000_000_000_000
CAM = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5, "cam")


class Bus:
    """Topics: publish serialises (CDR) and queues; one dispatcher thread runs the callbacks."""

    def __init__(self, drop=None):
        self.subs = defaultdict(list)
        self.published = defaultdict(list)
        self.drop = drop or (lambda topic, msg: False)
        self.q: queue.Queue = queue.Queue()
        self.errors = []
        self._stop = False
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def publish(self, topic, msg):
        name = msg.__msgtype__
        copy = TS.deserialize_cdr(TS.serialize_cdr(msg, name), name)
        self.published[topic].append(copy)
        if not self.drop(topic, copy):
            self.q.put((topic, copy))

    def _run(self):
        while not self._stop:
            try:
                topic, msg = self.q.get(timeout=0.05)
            except queue.Empty:
                continue
            for cb in list(self.subs[topic]):
                try:
                    cb(msg)
                except Exception as exc:  # a callback must never raise
                    self.errors.append((topic, exc))

    def idle(self):
        return self.q.empty()

    def close(self):
        self._stop = True
        self.thread.join(2)


class _Pub:
    def __init__(self, bus, topic):
        self.bus, self.topic = bus, topic

    def publish(self, msg):
        self.bus.publish(self.topic, msg)


class Context:
    """The NodeContext interface over a Bus."""

    def __init__(self, bus, name, **params):
        self.bus, self.name, self.types = bus, name, T
        self.config = config_from_params(params)
        self.on_change = None
        self.qos_events = 0
        self.logs = []
        self.timers = []
        self.qos = {}
        self.pub_qos, self.sub_qos = {}, {}   # by topic: what each publisher and subscription of this node asked for

    def log(self, level, message):
        self.logs.append((level, message))

    def now_ns(self):
        return time.time_ns()

    def resolve(self, topic):
        return topic if topic.startswith("/") else "/" + topic

    def publisher(self, msg_type, topic, *, kind=None, depth=None):
        self.qos[self.resolve(topic)] = self.pub_qos[self.resolve(topic)] = (kind or self.config.output_qos,
                                                                             depth or self.config.output_qos_depth)
        return _Pub(self.bus, self.resolve(topic))

    def subscription(self, msg_type, topic, callback, *, kind=None, depth=None):
        self.qos[self.resolve(topic)] = self.sub_qos[self.resolve(topic)] = (kind or self.config.input_qos,
                                                                             depth or self.config.input_qos_depth)
        self.bus.subs[self.resolve(topic)].append(callback)

    def timer(self, period, callback):
        self.timers.append(callback)
        return callback

    def tick(self):
        for cb in self.timers:
            cb()


def frame_messages(stamp_ns, color_size=(32, 24), holes=False):
    mm = np.full((24, 32), 2000, np.uint16)
    mm[6:18, 8:20] = 1200
    if holes:   # 2 x 6 pixels without depth, measured neighbours on both sides: depth_fill gives them a depth
        mm[2:4, 3:9] = 0
    w, h = color_size
    rgb = np.random.default_rng(stamp_ns % 997).integers(0, 256, (h, w, 3), dtype=np.uint8)
    rgb[..., 0] = 230
    hdr = msgbuild.make_header(T, stamp_ns, "cam")
    return {"/cam/info": msgbuild.camera_info_from_intrinsics(hdr, CAM, T), "/cam/depth": msgbuild.image_from_numpy(hdr, mm, T),
            "/cam/color": msgbuild.image_from_numpy(hdr, rgb, T)}


def params(model_path, **extra):
    p = {"model_path": str(model_path), "n0": 16, "n": 32, "axes": ["tx", "tz"], "radius.tx": 0.05, "input_mode": "rgbd",
         "depth_topic": "/cam/depth", "color_topic": "/cam/color", "camera_info_topic": "/cam/info", "preview_every": 2}
    p.update(extra)
    return p


def wait_for(cond, timeout=60, tick=()):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for ctx in tick:
            ctx.tick()
        if cond():
            return True
        time.sleep(0.02)
    return bool(cond())


def play(bus, stamps, got, wait=True, tick=()):
    for k, stamp in enumerate(stamps):
        for topic, msg in frame_messages(stamp).items():
            bus.publish(topic, msg)
        if wait:
            assert wait_for(lambda: len(got()) >= k + 1, tick=tick), f"no certification for frame {k}"


@pytest.fixture
def bus():
    b = Bus()
    yield b
    b.close()
    assert not b.errors, b.errors


@pytest.fixture
def model_path(make_model_file):
    return make_model_file(input_size=(24, 32))


def test_pipeline_one_certification_per_frame(bus, model_path):
    from pws_ros.nodes.pipeline import PipelineNode

    ctx = Context(bus, "pipeline", **params(model_path))
    node = PipelineNode(ctx)
    try:
        stamps = [T0 + k * 100_000_000 for k in range(3)]
        play(bus, stamps, lambda: bus.published["/certification"])
        certs = bus.published["/certification"]
        assert [msgconv.stamp_to_ns(m.header.stamp) for m in certs] == stamps
        for m in certs:
            parsed = msgbuild.parse_certification(m)
            assert list(parsed) == ["tx", "tz"] and m.header.frame_id == "cam"
            assert all(v["level"] in (0, 1) and v["class_name"] == "c1" and v["latency_ms"] > 0 for v in parsed.values())
        assert len(bus.published["/cloud"]) == 3 and len(bus.published["/cloud/camera_info"]) == 3
        poses = bus.published["/plan/poses/tx"]
        assert len(poses) == 3 and poses[0].header.frame_id == "cam"
        for pose_array, cert in zip(poses, certs):  # the poses the certificate rests on (refined per frame)
            assert len(pose_array.poses) == msgbuild.parse_certification(cert)["tx"]["num_partitions"]
        assert len(bus.published["/rendered/preview"]) > 0 and len(bus.published["/certification/markers"]) == 3
        # QoS: sensor data for camera inputs, reliable for results
        assert ctx.qos["/cam/depth"][0] == "sensor_data" and ctx.qos["/certification"][0] == "reliable"
        assert wait_for(lambda: node.worker.processed == 3 and not node.worker.busy)
        ctx.tick()  # health timer
        wait_for(bus.idle)
        (h,) = msgbuild.diagnostic_array_to_dicts(bus.published["/diagnostics"][-1])
        assert h["name"] == "pipeline: health" and h["level"] == 0
        assert h["values"]["frames_processed"] == "3" and h["values"]["frames_dropped"] == "0" and h["values"]["device"] == "cpu"
    finally:
        node.close()


def test_pipeline_online_policy_drops_old_frames(bus, model_path):
    from pws_ros.nodes.pipeline import PipelineNode

    node = PipelineNode(Context(bus, "pipeline", **params(model_path)))
    gate = threading.Event()
    process = node.worker.fn

    def gated(item):  # a certification slower than the camera
        gate.wait(30)
        process(item)

    node.worker.fn = gated
    try:
        stamps = [T0 + k * 10_000_000 for k in range(6)]
        play(bus, stamps, None, wait=False)
        assert wait_for(lambda: bus.idle() and node.frontend.assembler.frames == 6)
        st = node.worker.slot.stats()  # never a queue: at most one input waits for the worker
        assert st["pending"] <= 1 and st["accepted"] == 6 == st["taken"] + st["dropped"] + st["pending"]
        gate.set()

        def done():
            st = node.worker.slot.stats()
            return st["taken"] + st["dropped"] == 6 and node.worker.processed == st["taken"]

        assert wait_for(done)
        got = [msgconv.stamp_to_ns(m.header.stamp) for m in bus.published["/certification"]]
        assert got == sorted(got) and got[-1] == stamps[-1]  # the newest frame is always certified
        assert node.worker.processed in (1, 2) and node.worker.slot.dropped == 6 - node.worker.processed
        ctx_health = node._counters()
        assert ctx_health["frames_dropped"] == node.worker.slot.dropped and ctx_health["frames_in"] == 6
    finally:
        node.close()


def test_pipeline_reports_bad_input_as_error_statuses(bus, model_path):
    from pws_ros.nodes.pipeline import PipelineNode

    node = PipelineNode(Context(bus, "pipeline", **params(model_path)))
    try:
        msgs = frame_messages(T0, color_size=(40, 24))
        for topic, msg in msgs.items():
            bus.publish(topic, msg)
        assert wait_for(lambda: len(bus.published["/certification"]) == 1)
        parsed = msgbuild.parse_certification(bus.published["/certification"][0])
        for v in parsed.values():
            assert v["level"] == 2 and "not registered (different sizes)" in v["message"]
        assert not bus.published["/cloud"]
    finally:
        node.close()


def four_nodes(bus, model_path, **extra):
    from pws_ros.nodes.certifier import CertifierNode
    from pws_ros.nodes.cloud_listener import CloudListenerNode
    from pws_ros.nodes.partition_planner import PartitionPlannerNode
    from pws_ros.nodes.projector import ProjectorNode

    p = params(model_path, **extra)
    ctxs = {n: Context(bus, n, **p) for n in ("cloud_listener", "partition_planner", "projector", "certifier")}
    nodes = [CloudListenerNode(ctxs["cloud_listener"]), PartitionPlannerNode(ctxs["partition_planner"]),
             ProjectorNode(ctxs["projector"]), CertifierNode(ctxs["certifier"])]
    return ctxs, nodes


@pytest.mark.parametrize("output_qos", ["reliable", "best_effort", "sensor_data", "system_default"])
def test_four_processes_pair_every_topic_with_a_compatible_qos(model_path, output_qos):
    """Every topic one of the four nodes publishes and another reads is read with a reliability its writer offers
    (a reliable reader never matches a best-effort writer: with output_qos best_effort the certifier read 'plan'
    reliably, and no frame was ever certified)."""
    reliable = {"reliable": True, "system_default": True, "best_effort": False, "sensor_data": False}
    bus = Bus()
    try:
        ctxs, nodes = four_nodes(bus, model_path, output_qos=output_qos)
        pubs = {t: (n, q) for n, c in ctxs.items() for t, q in c.pub_qos.items()}
        pairs = [(t, pubs[t], n, q) for n, c in ctxs.items() for t, q in c.sub_qos.items() if t in pubs]
        assert {t for t, *_ in pairs} >= {"/cloud", "/plan", "/plan/cloud", "/rendered/frames", "/rendered/bounds"}
        bad = [f"{t}: {pn} writes {pq[0]}, {n} reads {q[0]}" for t, (pn, pq), n, q in pairs if reliable[q[0]] and not reliable[pq[0]]]
        assert not bad, bad
    finally:
        for node in nodes:
            node.close()
        bus.close()


@pytest.mark.parametrize("coverage", ["pairwise", "anchors"])
def test_four_processes_match_the_pipeline(model_path, coverage):
    """Same certificates from one process and from four: pairwise coverage; and the default adaptive
    anchors (the planner refines the grid for them, the certifier places them: the same anchors and p_A
    bounds, and without the pipeline's frontier refinement a radius that stops at a grid point)."""
    from pws_ros.nodes.pipeline import PipelineNode

    stamps = [T0 + k * 100_000_000 for k in range(2)]
    bus1 = Bus()
    pipe = PipelineNode(Context(bus1, "pipeline", **params(model_path, coverage=coverage)))
    try:
        play(bus1, stamps, lambda: bus1.published["/certification"])
    finally:
        pipe.close()
        bus1.close()
    bus2 = Bus()
    ctxs, nodes = four_nodes(bus2, model_path, coverage=coverage)
    try:
        play(bus2, stamps, lambda: bus2.published["/certification"], tick=[ctxs["certifier"]])
        assert not bus1.errors and not bus2.errors
        one, four = bus1.published["/certification"], bus2.published["/certification"]
        assert len(four) == 2
        for a, b in zip(one, four):
            assert a.header.stamp == b.header.stamp and a.header.frame_id == b.header.frame_id
            pa, pb = msgbuild.parse_certification(a), msgbuild.parse_certification(b)
            for axis in ("tx", "tz"):
                for key in ("label", "certified", "p_a_lower", "classifier_calls", "level"):
                    assert pa[axis][key] == pb[axis][key], (axis, key)
                if coverage == "pairwise":
                    assert pa[axis]["radius"] == pb[axis]["radius"] and pa[axis]["num_partitions"] == pb[axis]["num_partitions"]
                else:   # the same anchors; without the frontier refinement the radius stops at a grid point
                    assert 0 < pb[axis]["radius"] <= pa[axis]["radius"], axis
        n = sum(int(msgbuild.parse_certification(b)[ax]["num_partitions"]) for b in four for ax in ("tx", "tz"))
        assert len(bus2.published["/rendered/frames"]) == n and len(bus2.published["/rendered/bounds"]) == 4
        assert len(bus2.published["/plan"]) == 2 and len(bus2.published["/plan/poses/tz"]) == 2
        tag = scheme.parse_frame_tag(bus2.published["/rendered/frames"][0].header.frame_id)
        assert tag.stamp_ns == stamps[0] and tag.index == 0
    finally:
        for nd in nodes:
            nd.close()
        bus2.close()


def pipeline_and_four(model_path, publish, check=None, **extra) -> dict:
    """The pipeline, then the four processes, each on a fresh bus with ``params(model_path, **extra)``:
    ``publish(bus)`` plays the input, one certification is awaited, ``check(bus)`` runs before the nodes
    close. ``{"pipeline" | "four": (the parsed certification, the certifying node's Context)}``."""
    from pws_ros.nodes.pipeline import PipelineNode

    got = {}
    for name in ("pipeline", "four"):
        bus = Bus()
        if name == "pipeline":
            ctx = Context(bus, "pipeline", **params(model_path, **extra))
            nodes, tick = [PipelineNode(ctx)], []
        else:
            ctxs, nodes = four_nodes(bus, model_path, **extra)
            ctx, tick = ctxs["certifier"], [ctxs["certifier"]]
        try:
            publish(bus)
            assert wait_for(lambda: len(bus.published["/certification"]) == 1, tick=tick)
            got[name] = (msgbuild.parse_certification(bus.published["/certification"][0]), ctx)
            if check is not None:
                check(bus)
            assert not bus.errors
        finally:
            for nd in nodes:
                nd.close()
            bus.close()
    return got


def test_four_processes_state_the_filled_points_as_the_pipeline(model_path):
    """A depth image with 12 holes: the pipeline's certificates count 12 filled points, and so do the
    four processes' (the count crosses the cloud topic in the pws_filled field and the plan bundle)."""
    def publish(bus):
        for topic, msg in frame_messages(T0, holes=True).items():
            bus.publish(topic, msg)

    def check(bus):
        clouds = bus.published["/cloud"]
        assert len(clouds) == 1 and [f.name for f in clouds[0].fields][-1] == "pws_filled"
        assert int(cloudconv.cloud_from_pointcloud2(clouds[0]).cloud.filled) == 12

    got = {name: parsed for name, (parsed, _ctx) in pipeline_and_four(model_path, publish, check).items()}
    for axis in ("tx", "tz"):
        assert int(got["pipeline"][axis]["filled_points"]) == 12 == int(got["four"][axis]["filled_points"]), axis
        assert got["four"][axis]["level"] in (0, 1)


def test_four_processes_never_certify_an_incomplete_set(model_path):
    lost = []

    def drop(topic, msg):  # lose frame 1 of axis tx in transport, once
        if topic == "/rendered/frames" and msg.header.frame_id.split("/")[1:3] == ["tx", "1"] and not lost:
            lost.append(msg.header.frame_id)
            return True
        return False

    bus = Bus(drop=drop)
    ctxs, nodes = four_nodes(bus, model_path)
    try:
        play(bus, [T0], lambda: bus.published["/certification"], tick=[ctxs["certifier"]])
        parsed = msgbuild.parse_certification(bus.published["/certification"][0])
        assert parsed["tx"]["level"] == 2 and parsed["tx"]["certified"] is False
        assert "lost frame(s) 1" in parsed["tx"]["message"]
        assert parsed["tz"]["level"] in (0, 1)
        assert not bus.errors
    finally:
        for nd in nodes:
            nd.close()
        bus.close()


def test_four_processes_planning_errors_are_reported(model_path):
    bus = Bus()
    ctxs, nodes = four_nodes(bus, model_path, imaging="paper", axes=["rx", "tz"], **{"radius.rx": 1.5})
    try:
        play(bus, [T0], lambda: bus.published["/certification"], tick=[ctxs["certifier"]])
        parsed = msgbuild.parse_certification(bus.published["/certification"][0])
        assert parsed["rx"]["level"] == 2 and "turns a point behind the camera" in parsed["rx"]["message"]
        assert parsed["tz"]["level"] in (0, 1)
        plan = scheme.parse_plan_bundle_message(bus.published["/plan"][0])
        assert "rx" in plan.errors and "tz" in plan.plans
    finally:
        for nd in nodes:
            nd.close()
        bus.close()


def test_certifier_ignores_malformed_messages(bus, model_path):
    from pws_ros.nodes.certifier import CertifierNode

    ctx = Context(bus, "certifier", **params(model_path))
    node = CertifierNode(ctx)
    try:
        bus.publish("/plan", T.String(data="{not json"))
        bus.publish("/rendered/frames", msgbuild.image_from_numpy(msgbuild.make_header(T, 1, "garbage"), np.zeros((2, 2, 3), np.float32), T))
        bus.publish("/rendered/errors", T.String(data="[]"))
        assert wait_for(lambda: node.bad_messages == 3)
        assert not bus.published["/certification"]
        assert [lvl for lvl, _ in ctx.logs if lvl == "warn"]
    finally:
        node.close()


def test_four_processes_keep_up_with_a_fast_camera(model_path):
    """The camera runs faster than planning: many newer clouds arrive while a frame is planned, and
    the projector must still render the frame that was planned (the live ROS check found its cloud
    evicted by newer ones: 'no cloud with stamp ...'). The planner hands the planned cloud on."""
    bus = Bus()
    ctxs, nodes = four_nodes(bus, model_path)
    planner = nodes[1]
    slow_plan = planner.engine.plan_bundle

    def plan_bundle(*args, **kwargs):  # planning as slow as on a big cloud
        time.sleep(0.4)
        return slow_plan(*args, **kwargs)

    planner.engine.plan_bundle = plan_bundle

    def settled():  # nothing in transport, no worker busy or with work waiting
        nodes[3]._poll()  # the certifier's timer (its health timer would keep the bus busy)
        return bus.idle() and all(not n.worker.busy and not n.worker.slot.peek_full() for n in nodes)

    try:
        stamps = [T0 + k * 30_000_000 for k in range(30)]
        for stamp in stamps:  # a 33 Hz camera
            for topic, msg in frame_messages(stamp).items():
                bus.publish(topic, msg)
            time.sleep(0.03)
        planned = lambda: len(bus.published["/plan"])  # noqa: E731
        certs = bus.published["/certification"]
        assert wait_for(lambda: planned() >= 2 and settled() and (time.sleep(0.3) or settled()) and len(certs) >= 1)
        assert len(bus.published["/cloud"]) > 2 * planned()  # the camera did outrun the planner
        assert not bus.published["/rendered/errors"], [m.data for m in bus.published["/rendered/errors"]]
        for m in certs:  # (the certifier's own online policy may drop a frame, never fail one)
            for axis, v in msgbuild.parse_certification(m).items():
                assert v["level"] in (0, 1), (axis, v["message"])
        assert not bus.errors
    finally:
        for nd in nodes:
            nd.close()
        bus.close()


def test_unregistered_depth_is_refused_by_default(bus, model_path):
    """depth_camera_info_topic defaults to auto: the camera_info beside depth_topic. A depth camera
    that is not the colour camera (same size, other intrinsics: raw RealSense depth) is refused."""
    from pws_ros.nodes.pipeline import PipelineNode

    ctx = Context(bus, "pipeline", **params(model_path))
    node = PipelineNode(ctx)
    try:
        assert bus.subs["/cam/camera_info"]  # subscribed: beside /cam/depth
        other = CameraIntrinsics(32, 24, 20.0, 20.0, 16.0, 12.0, "cam")
        bus.publish("/cam/camera_info", msgbuild.camera_info_from_intrinsics(msgbuild.make_header(T, T0, "cam"), other, T))
        play(bus, [T0], lambda: bus.published["/certification"])
        parsed = msgbuild.parse_certification(bus.published["/certification"][0])
        assert all(v["level"] == 2 and "not registered" in v["message"] for v in parsed.values())
    finally:
        node.close()


def test_unregistered_depth_is_registered_with_the_extrinsic_from_tf_static(bus):
    """A RealSense-style camera without align_depth: depth in its own optical frame, related to the
    colour frame only through /tf_static (camera_link -> each optical frame). Refused until the
    transform arrives; then registered, and the cloud is the brute-force one written here."""
    from pws_ros.nodes.cloud_listener import CloudListenerNode

    # depth_fill off: the registered depth's own points (the fill is tested in test_depth_fill)
    ctx = Context(bus, "cloud_listener", **params("unused.pt", depth_camera_info_topic="/cam/depth_info", depth_fill="off"))
    node = CloudListenerNode(ctx)
    fx, cx, cy, z_mm, shift_m = CAM.fx, CAM.cx, CAM.cy, 3000, 0.2   # a 0.2 m baseline at 3 m: 2 px
    mm = np.full((24, 32), z_mm, np.uint16)
    mm[5:8, 10:14] = 0                                             # a hole stays a hole
    rgb = np.random.default_rng(5).integers(0, 256, (24, 32, 3), dtype=np.uint8)

    def publish_frame(stamp_ns):
        dh, ch = msgbuild.make_header(T, stamp_ns, "depth_optical"), msgbuild.make_header(T, stamp_ns, "color_optical")
        bus.publish("/cam/info", msgbuild.camera_info_from_intrinsics(ch, CAM, T))
        bus.publish("/cam/depth_info", msgbuild.camera_info_from_intrinsics(dh, CAM, T))
        bus.publish("/cam/depth", msgbuild.image_from_numpy(dh, mm, T))
        bus.publish("/cam/color", msgbuild.image_from_numpy(ch, rgb, T))

    def stamped(child, x):
        Tr, V, Q = TS.types["geometry_msgs/msg/Transform"], TS.types["geometry_msgs/msg/Vector3"], TS.types["geometry_msgs/msg/Quaternion"]
        return TS.types["geometry_msgs/msg/TransformStamped"](
            header=msgbuild.make_header(T, 0, "camera_link"), child_frame_id=child,
            transform=Tr(translation=V(x=x, y=0.0, z=0.0), rotation=Q(x=0.0, y=0.0, z=0.0, w=1.0)))

    try:
        assert ctx.qos["/tf_static"] == ("tf_static", 100)
        publish_frame(T0)
        assert wait_for(lambda: node.worker.processed + (node.worker.last_error != "") >= 1 and bus.idle(), 20)
        assert not bus.published["/cloud"] and "not registered" in node.worker.last_error
        # the colour optical frame sits 0.2 m left of the depth one (x to the right)
        bus.publish("/tf_static", T.TFMessage(transforms=[stamped("depth_optical", 0.0), stamped("color_optical", -shift_m)]))
        publish_frame(T0 + 100_000_000)
        assert wait_for(lambda: len(bus.published["/cloud"]) == 1, 20)
        assert any("registered into the colour camera" in m for _, m in ctx.logs)
        pts = cloud_xyz(bus.published["/cloud"][0])
        # brute force: each depth pixel moved into the colour frame, seen at its colour pixel
        expect = []
        z = z_mm / 1000.0
        for v in range(24):
            for u in range(32):
                if mm[v, u] == 0:
                    continue
                xc = (u - cx) * z / fx + shift_m
                uc = int(round(fx * xc / z + cx))
                if 0 <= uc < 32:
                    expect.append(((uc - cx) * z / fx, (v - cy) * z / CAM.fy, z))
        expect = np.array(sorted(expect))
        assert len(pts) == len(expect) == 24 * 32 - 12 - 2 * 24
        np.testing.assert_allclose(pts[np.lexsort(pts.T[::-1])], expect, atol=1e-5)
    finally:
        node.close()


def test_a_worker_busy_at_close_is_reported_until_it_ends():
    """A frame still in flight when the node closes (shutdown is polled between axes) is named by
    still_running_workers, which makes _ros.run end the process without tearing torch down under it."""
    from pws_ros.nodes._common import Worker, still_running_workers

    started, release = threading.Event(), threading.Event()

    def slow(_item):
        started.set()
        release.wait(10)

    logs = []
    w = Worker("pws-test-busy", slow, lambda lvl, msg: logs.append((lvl, msg)))
    idle = Worker("pws-test-idle", slow, lambda lvl, msg: logs.append((lvl, msg)))
    assert "pws-test-busy" not in still_running_workers()  # running, but not asked to stop
    w.submit(1)
    assert started.wait(5)
    w.close(timeout=0.1)
    idle.close(timeout=2)
    assert "pws-test-busy" in still_running_workers() and "pws-test-idle" not in still_running_workers()
    release.set()
    w.thread.join(5)
    assert "pws-test-busy" not in still_running_workers() and not logs


def test_four_processes_a_replanned_frame_the_projector_drops_is_no_error(model_path):
    """A looped bag plans a stamp again; when the busy projector drops that plan (its online policy),
    the certifier must not open a set that times out into an ERROR certification (seen live)."""
    bus = Bus()
    ctxs, nodes = four_nodes(bus, model_path, assembly_timeout_s=0.5)
    projector, certifier = nodes[2], nodes[3]
    a, b = T0, T0 + 100_000_000
    skipped = []
    submit = projector.worker.submit

    def busy_projector(bundle):  # pass 2: stamp a is dropped by the projector's online policy
        if bundle.stamp_ns == a and len(bus.published["/certification"]) >= 2:
            skipped.append(bundle.stamp_ns)
            return True
        return submit(bundle)

    projector.worker.submit = busy_projector
    try:
        certs = bus.published["/certification"]
        play(bus, [a, b], lambda: certs, tick=[ctxs["certifier"]])
        for topic, msg in frame_messages(a).items():  # the loop: a again, dropped by the projector
            bus.publish(topic, msg)
        assert wait_for(lambda: skipped and bus.idle())
        play(bus, [b], lambda: certs[2:], tick=[ctxs["certifier"]])
        time.sleep(1.0)  # twice the assembly timeout
        certifier._poll()  # its timer: what timed out is released now
        assert wait_for(lambda: bus.idle() and not certifier.worker.busy and not certifier.worker.slot.peek_full())
        assert stamps_of(certs) == [a, b, b]
        assert all(v["level"] in (0, 1) for m in certs for v in msgbuild.parse_certification(m).values())
        assert certifier.assembler.failed == 0
        assert certifier.assembler.time_jumps == 1
    finally:
        for nd in nodes:
            nd.close()
        bus.close()
    assert not bus.errors, bus.errors


def stamps_of(msgs):
    return [msgconv.stamp_to_ns(m.header.stamp) for m in msgs]


def cloud_xyz(msg):
    """The finite x, y, z (float32 little-endian fields) of a PointCloud2, read with numpy here."""
    assert not msg.is_bigendian
    offsets = {f.name: f.offset for f in msg.fields}
    rows = np.frombuffer(bytes(msg.data), np.uint8).reshape(-1, msg.point_step)
    xyz = np.stack([rows[:, offsets[a]:offsets[a] + 4].copy().view("<f4")[:, 0] for a in "xyz"], axis=1).astype(np.float64)
    return xyz[np.isfinite(xyz).all(axis=1)]


def test_pipeline_pairs_unsynced_depth_and_colour_with_a_warning(bus, model_path):
    """A driver whose depth and colour are 60 ms apart (beyond sync_tolerance_s, within sync_max_skew_s):
    the pair is certified once a later colour frame settles it, and one WARN names the skew."""
    from pws_ros.nodes.pipeline import PipelineNode

    ctx = Context(bus, "pipeline", **params(model_path, axes=["tz"]))
    node = PipelineNode(ctx)
    try:
        ms = 1_000_000
        for stamp, topics in ((T0, ("/cam/info", "/cam/color")), (T0 + 60 * ms, ("/cam/depth",)),
                              (T0 + 500 * ms, ("/cam/color",)), (T0 + 560 * ms, ("/cam/depth",))):
            msgs = frame_messages(stamp)
            for topic in topics:
                bus.publish(topic, msgs[topic])
        assert wait_for(lambda: len(bus.published["/certification"]) >= 1)
        cert = bus.published["/certification"][0]
        assert msgconv.header_stamp_ns(cert) == T0                       # the colour frame's stamp
        skew = [m for lv, m in ctx.logs if lv == "warn" and "60.0 ms apart" in m]
        assert len(skew) == 1 and "sync_max_skew_s" in skew[0]
        time.sleep(0.3)
        assert len(bus.published["/certification"]) == 1                  # the last depth waits to be settled
    finally:
        node.close()


def test_two_pipeline_workers_certify_every_stamp_once_as_one_worker_does(model_path):
    """workers:=2 without ROS: two pipeline nodes on one input stream (num_workers 2, worker_index 0/1,
    worker_period_s = the camera period) publish one certification per stamp between them, each on its
    own stamps, equal to what a single pipeline publishes for the same stamps (latency, compute time and
    the node's name aside)."""
    import torch

    from pws_ros.nodes.pipeline import PipelineNode

    threads = torch.get_num_threads()
    stamps = [T0 + k * 100_000_000 for k in range(4)]
    shared = Bus()
    alone = Bus()
    nodes = []
    try:
        nodes = [PipelineNode(Context(shared, f"pipeline_{i}", **params(model_path, num_workers=2, worker_index=i,
                                                                        worker_period_s=0.1))) for i in range(2)]
        assert torch.get_num_threads() == max(1, threads // 2) or threads == 1
        nodes.append(PipelineNode(Context(alone, "pipeline", **params(model_path))))
        play(shared, stamps, lambda: shared.published["/certification"])
        play(alone, stamps, lambda: alone.published["/certification"])
        assert wait_for(lambda: all(n.worker.processed + n.worker.slot.dropped == 2 for n in nodes[:2]) and shared.idle())
        got = shared.published["/certification"]
        assert sorted(msgconv.stamp_to_ns(m.header.stamp) for m in got) == stamps   # each stamp exactly once
        assert [n.worker.processed for n in nodes[:2]] == [2, 2] and [n.other_workers for n in nodes[:2]] == [2, 2]
        by_node = {}
        for m in got:
            (status,) = {v["node"] for v in msgbuild.parse_certification(m).values()}
            by_node.setdefault(status, []).append(msgconv.stamp_to_ns(m.header.stamp) // 100_000_000 % 2)
        assert by_node == {"pipeline_0": [0, 0], "pipeline_1": [1, 1]}

        def values(msgs):
            out = {}
            for m in msgs:
                parsed = msgbuild.parse_certification(m)
                for v in parsed.values():
                    for k in ("latency_ms", "compute_ms", "node"):
                        v.pop(k)
                out[msgconv.stamp_to_ns(m.header.stamp)] = parsed
            return out

        assert values(got) == values(alone.published["/certification"])
        assert nodes[0]._counters()["extra"]["other_workers_frames"] == 2
    finally:
        for n in nodes:
            n.close()
        shared.close()
        alone.close()
        torch.set_num_threads(threads)
    assert not shared.errors and not alone.errors
