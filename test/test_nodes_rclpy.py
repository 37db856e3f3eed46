"""End-to-end node tests with real rclpy (skipped where ROS 2 Jazzy is not installed).

A player node publishes a few synthetic RGB-D frames (waiting for each result, so none is dropped by
the online policy) through (a) the one-process ``pipeline`` and (b) the four nodes
(cloud_listener -> partition_planner -> projector -> certifier) in one executor, and checks one
``certification`` message per frame with the documented key schema; plus parameter validation.
"""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

pytestmark = pytest.mark.rclpy

FRAMES = 3
T0 = 1_700_000_000_000_000_000
AXES = ["tz", "ry"]


def wait_for(cond, timeout):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.05)
    return bool(cond())


@pytest.fixture
def ros():
    rclpy = pytest.importorskip("rclpy", reason="rclpy (ROS 2 Jazzy) is not installed")
    rclpy.init()
    yield rclpy
    rclpy.try_shutdown()


def frame_messages(T, stamp_ns):
    from pws_ros.bridge import msgbuild
    from pws_ros.core.camera import CameraIntrinsics

    cam = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5, "cam")
    mm = np.full((24, 32), 2000, np.uint16)
    mm[6:18, 8:20] = 1200
    rgb = np.random.default_rng(stamp_ns % 1000).integers(0, 256, (24, 32, 3), dtype=np.uint8)
    rgb[..., 0] = 230
    hdr = msgbuild.make_header(T, stamp_ns, "cam")
    return (msgbuild.camera_info_from_intrinsics(hdr, cam, T), msgbuild.image_from_numpy(hdr, mm, T),
            msgbuild.image_from_numpy(hdr, rgb, T))


def parameters(model_path):
    from rclpy.parameter import Parameter

    return [Parameter("model_path", value=str(model_path)), Parameter("n0", value=16), Parameter("n", value=32),
            Parameter("axes", value=AXES), Parameter("input_mode", value="rgbd"), Parameter("depth_topic", value="/cam/depth"),
            Parameter("color_topic", value="/cam/color"), Parameter("camera_info_topic", value="/cam/info"),
            Parameter("health_period_s", value=0.2), Parameter("assembly_timeout_s", value=60.0)]


def play_and_collect(nodes, logics):
    """Publish FRAMES frames one at a time; return the certification messages and health statuses."""
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.node import Node

    from pws_ros.bridge import msgbuild
    from pws_ros.nodes._ros import qos, rclpy_types

    T = rclpy_types()
    player = Node("player")
    pubs = [player.create_publisher(T.CameraInfo, "/cam/info", qos("reliable", 10)),
            player.create_publisher(T.Image, "/cam/depth", qos("reliable", 10)),
            player.create_publisher(T.Image, "/cam/color", qos("reliable", 10))]
    got, health = [], []
    player.create_subscription(T.DiagnosticArray, "/certification", got.append, qos("reliable", 50))
    player.create_subscription(T.DiagnosticArray, "/diagnostics", health.append, qos("reliable", 50))
    ex = MultiThreadedExecutor(num_threads=4)
    for n in nodes + [player]:
        ex.add_node(n)
    th = threading.Thread(target=ex.spin, daemon=True)
    th.start()
    try:
        assert wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs), 20), "the node did not subscribe"
        for k in range(FRAMES):
            for p, m in zip(pubs, frame_messages(T, T0 + k * 100_000_000)):
                p.publish(m)
            assert wait_for(lambda: len(got) >= k + 1, 180), f"no certification for frame {k}"
        time.sleep(0.5)
        assert wait_for(lambda: len(health) > 0, 10)
        return got, [d for h in health for d in msgbuild.diagnostic_array_to_dicts(h)]
    finally:
        for logic in logics:
            logic.close()
        ex.shutdown()
        player.destroy_node()


def check_certifications(got):
    from pws_ros.bridge import msgbuild, msgconv

    assert len(got) == FRAMES  # exactly one per frame
    for k, msg in enumerate(got):
        assert msgconv.stamp_to_ns(msg.header.stamp) == T0 + k * 100_000_000
        assert msg.header.frame_id == "cam"
        parsed = msgbuild.parse_certification(msg)
        assert list(parsed) == AXES
        for axis, v in parsed.items():
            assert v["level"] in (0, 1), v["message"]
            assert v["class_name"] == "c1" and v["n"] == 32 and v["sigma"] == 0.5 and v["hardware_id"] == "cam"
        for st in msgbuild.diagnostic_array_to_dicts(msg):
            assert tuple(st["keys"][:14]) == msgbuild.DIAGNOSTIC_KEYS


def test_pipeline_one_certification_per_frame(ros, make_model_file):
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from pws_ros.nodes._ros import NodeContext
    from pws_ros.nodes.pipeline import PipelineNode

    node = Node("pipeline", parameter_overrides=parameters(make_model_file(input_size=(24, 32))))
    logic = PipelineNode(NodeContext(node, "pipeline"))
    try:
        got, health = play_and_collect([node], [logic])
        check_certifications(got)
        assert any(h["name"] == "pipeline: health" and h["values"]["device"] == "cpu" for h in health)
        # parameters: validated on set, read-only where it matters
        bad = node.set_parameters([Parameter("method", value="pws")])[0]
        assert not bad.successful and "dense_cloud_path" in bad.reason
        assert not node.set_parameters([Parameter("sigma", value=-1.0)])[0].successful
        assert not node.set_parameters([Parameter("model_path", value="other.pt")])[0].successful
        assert node.set_parameters([Parameter("sigma", value=0.25)])[0].successful
        assert wait_for(lambda: logic.ctx.config.sigma == 0.25, 5)
        desc = node.describe_parameter("sigma")
        assert desc.description and desc.floating_point_range[0].to_value == 10.0
    finally:
        node.destroy_node()


def test_four_nodes_one_certification_per_frame(ros, make_model_file):
    from rclpy.node import Node

    from pws_ros.nodes._ros import NodeContext
    from pws_ros.nodes.certifier import CertifierNode
    from pws_ros.nodes.cloud_listener import CloudListenerNode
    from pws_ros.nodes.partition_planner import PartitionPlannerNode
    from pws_ros.nodes.projector import ProjectorNode

    params = parameters(make_model_file(input_size=(24, 32)))
    classes = {"cloud_listener": CloudListenerNode, "partition_planner": PartitionPlannerNode,
               "projector": ProjectorNode, "certifier": CertifierNode}
    nodes, logics = [], []
    for name, cls in classes.items():
        node = Node(name, parameter_overrides=[p for p in params if _uses(name, p.name)])
        nodes.append(node)
        logics.append(cls(NodeContext(node, name)))
    try:
        got, health = play_and_collect(nodes, logics)
        check_certifications(got)
        names = {h["name"] for h in health}
        assert {f"{n}: health" for n in classes} <= names
    finally:
        for n in nodes:
            n.destroy_node()


def _uses(node_name, param):
    from pws_ros.bridge.params import SPECS

    return node_name in SPECS[param].nodes


def test_health_goes_on_when_sim_time_stops(ros, make_model_file):
    """With use_sim_time and no /clock (a paused or finished `ros2 bag play --clock`) the node clock
    stands still; health reports (and the certifier's hand-over timer) run on the steady clock."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from pws_ros.nodes._ros import NodeContext, qos, rclpy_types
    from pws_ros.nodes.pipeline import PipelineNode

    params = parameters(make_model_file(input_size=(24, 32))) + [Parameter("use_sim_time", value=True)]
    node = Node("pipeline", parameter_overrides=params)
    logic = PipelineNode(NodeContext(node, "pipeline"))
    listener = Node("health_listener")
    health = []
    listener.create_subscription(rclpy_types().DiagnosticArray, "/diagnostics", health.append, qos("reliable", 50))
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    ex.add_node(listener)
    try:
        end = time.monotonic() + 5.0
        while time.monotonic() < end and len(health) < 3:
            ex.spin_once(timeout_sec=0.1)
        assert node.get_clock().now().nanoseconds == 0  # sim time, no /clock
        assert len(health) >= 3
    finally:
        logic.close()
        ex.shutdown()
        listener.destroy_node()
        node.destroy_node()


def test_incompatible_qos_is_logged_and_counted(ros, make_model_file):
    """A best-effort camera against a node told to subscribe reliably: no message can flow, and the
    node says so (warning + qos_incompatible_events) instead of waiting silently."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from pws_ros.nodes._ros import NodeContext, qos, rclpy_types
    from pws_ros.nodes.pipeline import PipelineNode

    params = parameters(make_model_file(input_size=(24, 32))) + [Parameter("input_qos", value="reliable")]
    node = Node("pipeline", parameter_overrides=params)
    ctx = NodeContext(node, "pipeline")
    logic = PipelineNode(ctx)
    camera = Node("best_effort_camera")
    pub = camera.create_publisher(rclpy_types().Image, "/cam/color", qos("best_effort", 5))
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    ex.add_node(camera)
    try:
        end = time.monotonic() + 10.0
        while time.monotonic() < end and ctx.qos_events == 0:
            ex.spin_once(timeout_sec=0.1)
        assert ctx.qos_events >= 1
        assert pub.get_subscription_count() == 0  # not matched: nothing would ever arrive
    finally:
        logic.close()
        ex.shutdown()
        camera.destroy_node()
        node.destroy_node()


def test_cloud_listener_registers_depth_with_latched_tf_static(ros):
    """/tf_static published (transient local, as tf2's static broadcaster does) before the node
    starts still reaches it; unregistered depth is then registered and converted, not refused."""
    from geometry_msgs.msg import TransformStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from pws_ros.bridge import msgbuild
    from pws_ros.core.camera import CameraIntrinsics
    from pws_ros.nodes._ros import NodeContext, qos, rclpy_types
    from pws_ros.nodes.cloud_listener import CloudListenerNode

    T = rclpy_types()

    driver = Node("camera_driver")
    tf_pub = driver.create_publisher(T.TFMessage, "/tf_static", qos("tf_static", 1))
    links = []
    for child, x in (("depth_optical", 0.0), ("color_optical", -0.2)):
        ts = TransformStamped()
        ts.header.frame_id, ts.child_frame_id = "camera_link", child
        ts.transform.translation.x, ts.transform.rotation.w = x, 1.0
        links.append(ts)
    tf_pub.publish(T.TFMessage(transforms=links))  # before the listener exists: latched
    params = [Parameter("input_mode", value="rgbd"), Parameter("depth_topic", value="/cam/depth"),
              Parameter("color_topic", value="/cam/color"), Parameter("camera_info_topic", value="/cam/info"),
              Parameter("depth_camera_info_topic", value="/cam/depth_info"),
              Parameter("depth_fill", value="off")]   # the registration's holes stay holes (row fill would close them)
    node = Node("cloud_listener", parameter_overrides=params)
    logic = CloudListenerNode(NodeContext(node, "cloud_listener"))
    clouds = []
    driver.create_subscription(T.PointCloud2, "/cloud", clouds.append, qos("reliable", 5))
    names = ("/cam/info", "/cam/depth_info", "/cam/depth", "/cam/color")
    pubs = [driver.create_publisher(T.CameraInfo if "info" in t else T.Image, t, qos("reliable", 5)) for t in names]
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    ex.add_node(driver)

    def spin_until(cond, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end and not cond():
            ex.spin_once(timeout_sec=0.05)
        return cond()

    try:
        assert spin_until(lambda: logic.frontend.static_tf.messages > 0, 20), "the latched /tf_static did not arrive"
        assert spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs), 20)
        cam = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)
        dh, ch = msgbuild.make_header(T, T0, "depth_optical"), msgbuild.make_header(T, T0, "color_optical")
        pubs[0].publish(msgbuild.camera_info_from_intrinsics(ch, cam, T))
        pubs[1].publish(msgbuild.camera_info_from_intrinsics(dh, cam, T))
        asm = logic.frontend.assembler
        assert spin_until(lambda: asm.latest_info is not None and asm.latest_depth_info is not None, 20)
        pubs[2].publish(msgbuild.image_from_numpy(dh, np.full((24, 32), 3000, np.uint16), T))
        pubs[3].publish(msgbuild.image_from_numpy(ch, np.zeros((24, 32, 3), np.uint8), T))
        assert spin_until(lambda: len(clouds) == 1, 30), f"no cloud (worker: {logic.worker.last_error!r})"
        assert logic.frontend.static_tf.extrinsic is not None
        from test_nodes_logic import cloud_xyz

        xyz = cloud_xyz(clouds[0])
        # 0.2 m baseline at 3 m and fx 30: depth shifted 2 px to the right; the 2 leftmost columns are holes
        assert len(xyz) == 24 * 30 and np.allclose(xyz[:, 2], 3.0)
        assert np.isclose(xyz[:, 0].min(), (2 - 15.5) * 3.0 / 30.0, atol=1e-5)
    finally:
        logic.close()
        ex.shutdown()
        driver.destroy_node()
        node.destroy_node()
