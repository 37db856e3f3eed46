"""Issue 26: hostile or malformed messages on the four-process topics (and on the inputs). Every input
frame that enters the four-process chain ends in exactly one certification message (certified, not
certified, abstained or ERROR), one test per malformed case class, driven through the node classes
with the in-memory context of test_nodes_logic (rosbags messages after a CDR round trip; this is not
a stand-in for rclpy). Also the parsers' own refusals of the crashes seen live (NaN bounds shape, a
plan with ``"axes": 5`` or ``"stamp_ns": "x"``, a frame tag with a billion frames)."""
from __future__ import annotations

import json
import math
import subprocess
import sys
import time

import numpy as np
import pytest

from pws_ros.bridge import msgbuild, msgconv, scheme
from pws_ros.bridge.assembly import PartitionAssembler
from pws_ros.core.errors import PwsError
from test_nodes_logic import T, T0, Bus, Context, bus, four_nodes, frame_messages, params, stamps_of, wait_for  # noqa: F401 (bus: a fixture)

MS = 1_000_000
A, B = T0, T0 + 100 * MS     # the hostile frame, then a valid one


@pytest.fixture
def model_path(make_model_file):
    return make_model_file(input_size=(24, 32))


def plan_stamp(msg):
    return json.loads(msg.data).get("stamp_ns")


class Case:
    """A Bus ``drop`` hook that corrupts what the chain publishes about frame A (the hook sees every
    message before it is delivered: return True to drop it; ``bus.q.put`` delivers one now)."""

    def __init__(self):
        self.bus = None
        self.done = []

    def __call__(self, topic, msg):
        return False


class BadPlan(Case):          # the planner's plan for A arrives malformed (it names its stamp)
    def __call__(self, topic, msg):
        if topic == "/plan" and plan_stamp(msg) == A and not self.done:
            d = json.loads(msg.data)
            d["axes"] = 5
            self.done.append(1)
            self.bus.q.put((topic, T.String(data=json.dumps(d))))
            return True
        return False


class BadCloudAfterPlan(Case):  # plan/cloud of A is held back and arrives after the plan, malformed (is_bigendian wrong)
    def __init__(self):
        super().__init__()
        self.cloud = None

    def __call__(self, topic, msg):
        if topic == "/plan/cloud" and msgconv.header_stamp_ns(msg) == A and self.cloud is None:
            self.cloud = msg
            return True
        if topic == "/plan" and plan_stamp(msg) == A and self.cloud is not None and not self.done:
            self.done.append(1)
            self.bus.q.put((topic, msg))
            self.cloud.is_bigendian = True
            self.bus.q.put(("/plan/cloud", self.cloud))
            return True
        return False


class NanBoundsShape(Case):   # rendered/bounds of A, axis tz, with NaN height and width
    def __call__(self, topic, msg):
        if topic == "/rendered/bounds" and msg.layout.dim[0].label.startswith(f"pws_bounds/{A}/tz/") and not self.done:
            self.done.append(1)
            data = np.array(msg.data, dtype=np.float64)
            data[-2:] = np.nan
            msg.data = data
        return False


class HugeFrameCount(Case):   # a rendered frame of A, axis tz, tagged with a billion frames
    def __call__(self, topic, msg):
        if topic == "/rendered/frames" and msg.header.frame_id == f"{A}/tz/0/{msg.header.frame_id.split('/')[-1]}" and not self.done:
            self.done.append(1)
            msg.header.frame_id = f"{A}/tz/999999999/1000000000"
        return False


def nan_distortion(msgs):
    info = msgs["/cam/info"]
    info.distortion_model = "fisheye_unknown"
    info.d = np.array([math.nan, 0.0, 0.0, 0.0, 0.0])
    return msgs


def one_valid_depth(msgs):
    """A depth image with a single valid pixel: certified before (a certificate about a made-up scene)."""
    mm = np.zeros((24, 32), np.uint16)
    mm[12, 16] = 1500
    msgs["/cam/depth"] = msgbuild.image_from_numpy(msgs["/cam/depth"].header, mm, T)
    return msgs


def unregistered(msgs):
    return frame_messages(A, color_size=(40, 24))


CASES = {
    # case class: (how frame A is corrupted, the axes that must be ERROR, a phrase of the ERROR's message)
    "input not registered": (unregistered, None, ("tx", "tz"), "not registered (different sizes)"),
    "CameraInfo NaN coefficients": (nan_distortion, None, ("tx", "tz"), "CameraInfo D[0] is nan"),
    "depth with one valid pixel": (one_valid_depth, None, ("tx", "tz"), "below min_valid_depth"),
    "plan with axes 5": (None, BadPlan, ("tx", "tz"), "malformed plan message"),
    "plan/cloud malformed after its plan": (None, BadCloudAfterPlan, ("tx", "tz"), "is_bigendian"),
    "bounds with NaN shape": (None, NanBoundsShape, ("tz",), "malformed bounds message"),
    "frame tag with a billion frames": (None, HugeFrameCount, ("tz",), "more than max_partitions"),
}


def settle(bus, nodes, certifier):
    def quiet():
        certifier._poll()
        return bus.idle() and all(not n.worker.busy and not n.worker.slot.peek_full() for n in nodes)
    assert wait_for(lambda: quiet() and (time.sleep(0.3) or quiet()), 60)


@pytest.mark.parametrize("name", list(CASES))
def test_every_frame_of_the_chain_ends_in_exactly_one_certification(model_path, name):
    corrupt_input, hook_class, error_axes, phrase = CASES[name]
    hook = hook_class() if hook_class else Case()
    bus = Bus(drop=hook)
    hook.bus = bus
    ctxs, nodes = four_nodes(bus, model_path)
    certs = bus.published["/certification"]
    try:
        for k, stamp in enumerate((A, B)):
            msgs = frame_messages(stamp)
            if stamp == A and corrupt_input:
                msgs = corrupt_input(msgs)
            for topic, msg in msgs.items():
                bus.publish(topic, msg)
            assert wait_for(lambda: len(certs) >= k + 1, 60, tick=[ctxs["certifier"]]), f"{name}: no certification for frame {k}"
        settle(bus, nodes, nodes[3])
        assert hook_class is None or hook.done, "the case did not apply"
        assert stamps_of(certs) == [A, B], f"{name}: one certification per frame, got {stamps_of(certs)}"
        bad, good = (msgbuild.parse_certification(m) for m in certs)
        for axis, v in bad.items():
            if axis in error_axes:
                assert v["level"] == 2 and v["status"] == "error" and phrase in v["message"], (axis, v["message"])
            else:
                assert v["level"] in (0, 1), (axis, v["message"])
        assert all(v["level"] in (0, 1) for v in good.values()), good   # the chain goes on
        assert not bus.errors, bus.errors                                 # no callback raised
    finally:
        for nd in nodes:
            nd.close()
        bus.close()


def test_a_negative_stamp_is_certified_in_both_modes(model_path):
    """A frame stamped -5 s (a valid ROS time: sec = -5) is certified by the pipeline and, now, by the
    four-process chain too (its frame tags and headers could not carry a negative stamp before)."""
    from pws_ros.nodes.pipeline import PipelineNode

    stamp = -5_000_000_000
    results = {}
    for mode in ("pipeline", "four"):
        bus = Bus()
        if mode == "pipeline":
            ctx = Context(bus, "pipeline", **params(model_path))
            nodes, tick = [PipelineNode(ctx)], []
        else:
            ctxs, nodes = four_nodes(bus, model_path)
            tick = [ctxs["certifier"]]
        try:
            for topic, msg in frame_messages(stamp).items():
                bus.publish(topic, msg)
            assert wait_for(lambda: len(bus.published["/certification"]) >= 1, 60, tick=tick), mode
            time.sleep(0.3)
            certs = bus.published["/certification"]
            assert stamps_of(certs) == [stamp] and certs[0].header.stamp.sec == -5 and not bus.errors
            results[mode] = msgbuild.parse_certification(certs[0])
        finally:
            for nd in nodes:
                nd.close()
            bus.close()
    for axis in ("tx", "tz"):
        assert results["pipeline"][axis]["level"] in (0, 1) and results["four"][axis]["level"] in (0, 1)
        assert results["pipeline"][axis]["label"] == results["four"][axis]["label"]


def test_malformed_messages_that_name_no_frame_are_warned_not_certified(bus, model_path):
    """A plan whose stamp is not an integer, a render error that is not one: a throttled WARN naming the
    topic, counted; nothing is certified (no frame is named), nothing raises."""
    from pws_ros.nodes.certifier import CertifierNode

    ctx = Context(bus, "certifier", **params(model_path))
    node = CertifierNode(ctx)
    try:
        bad_plan = {"format": scheme.PLAN_FORMAT, "stamp_ns": "x", "frame_id": "cam", "method": "pws_of", "axes": ["tz"],
                    "camera": {"width": 4, "height": 3, "fx": 1, "fy": 1, "cx": 1, "cy": 1}}
        bus.publish("/plan", T.String(data=json.dumps(bad_plan)))
        bus.publish("/rendered/errors", T.String(data='{"format": "pws_ros/render-error/1", "stamp_ns": 1e400, "axis": "tz"}'))
        assert wait_for(lambda: node.bad_messages == 2 and bus.idle())
        node._poll()
        assert not bus.published["/certification"]
        warns = [m for lvl, m in ctx.logs if lvl == "warn"]
        assert any(m.startswith("plan: ignoring a message: plan stamp_ns must be an integer") for m in warns), warns
    finally:
        node.close()


# ---- the parsers' refusals (ROS-free) ----

def test_the_crashes_seen_live_are_refusals():
    base = {"format": scheme.PLAN_FORMAT, "stamp_ns": 7, "frame_id": "cam", "method": "pws_of", "axes": ["tz"],
            "camera": {"width": 4, "height": 3, "fx": 1, "fy": 1, "cx": 1, "cy": 1}, "errors": {"tz": "x"}}
    for change, phrase in (({"axes": 5}, "plan axes must be a list"), ({"stamp_ns": "x"}, "stamp_ns must be an integer"),
                           ({"stamp_ns": 1.5}, "stamp_ns must be an integer"), ({"camera": [1]}, "camera must be a mapping"),
                           ({"axes": ["tz", "tz"]}, "an axis twice"), ({"plans": {"tz": {"alphas": "abc"}}}, "no list of alphas"),
                           ({"errors": {"tz": "x", "rx": "y"}}, "axes it does not list")):
        with pytest.raises(PwsError, match=phrase):
            scheme.plan_bundle_from_json(json.dumps({**base, **change}))
    assert scheme.plan_bundle_stamp(json.dumps({**base, "axes": 5})) == 7      # the frame a malformed plan names
    assert scheme.plan_bundle_stamp(json.dumps({**base, "stamp_ns": "x"})) is None
    # a plan of more frames than the receiver's max_partitions is refused before Plan.from_dict builds it
    with pytest.raises(PwsError, match="more than max_partitions 5"):
        scheme.plan_bundle_from_json(json.dumps({**base, "plans": {"tz": {"alphas": [0.0] * 6}}, "errors": {}}), max_count=5)

    def bounds(label="pws_bounds/7/tz/3", data=(0.1, 0.2, float("nan"), float("nan")), nextra=0):
        dims = [T.MultiArrayDimension(label=label, size=2, stride=2), T.MultiArrayDimension(label="extra", size=nextra, stride=5 * nextra),
                T.MultiArrayDimension(label="shape", size=2, stride=2)]
        return T.Float64MultiArray(layout=T.MultiArrayLayout(dim=dims, data_offset=0), data=np.array(data, dtype=np.float64))

    with pytest.raises(PwsError, match="frame shape nan x nan is not two positive integers"):
        scheme.parse_bounds_message(bounds())
    with pytest.raises(PwsError, match="pixel index"):
        scheme.parse_bounds_message(bounds(data=(0.1, 0.2, 0, 999, 0.5, 0.5, 0.5, 2, 2), nextra=1))
    with pytest.raises(PwsError, match="segment index"):
        scheme.parse_bounds_message(bounds(data=(0.1, 0.2, 5, 0, 0.5, 0.5, 0.5, 2, 2), nextra=1))
    with pytest.raises(PwsError, match="pair bound is negative"):
        scheme.parse_bounds_message(bounds(data=(-0.1, 0.2, 2, 2)))
    with pytest.raises(PwsError, match="more than max_partitions"):
        scheme.parse_bounds_message(bounds(label="pws_bounds/7/tz/1000000000"), max_count=257)
    assert scheme.tag_owner("pws_bounds/7/tz/1000000000") == (7, "tz") and scheme.tag_owner("7/tz/999999999/1000000000") == (7, "tz")
    ok = scheme.parse_bounds_message(bounds(data=(0.1, 0.2, 1, 5, 0.5, 0.5, 0.5, 2, 3), nextra=1))
    assert ok.shape == (2, 3) and ok.seg.tolist() == [1] and ok.pix.tolist() == [5]


def test_the_assembler_never_enumerates_a_count_from_a_message():
    """A frame tagged with a billion frames (no plan yet) and then lost frames, released by a timeout: the
    message names the runs, built from the frames present, never one item per index. Run in a child
    process under a 1.5 GB address-space limit, so that a regression fails here instead of taking the
    machine's memory (list(range(10**9)) needs tens of GB)."""
    code = r"""
import resource
resource.setrlimit(resource.RLIMIT_AS, (1536 * 2**20, 1536 * 2**20))
from pws_ros.bridge.assembly import PartitionAssembler
clock = [0.0]
asm = PartitionAssembler(timeout_s=1, clock=lambda: clock[0])
asm.add_frame(7, "tz", 0, 1_000_000_000, b"x")
asm.add_frame(7, "tz", 2, 1_000_000_000, b"x")       # a gap: lost frame 1
asm.add_frame(8, "tz", 999_999_998, 1_000_000_000, b"x")  # a gap of a billion
clock[0] = 5.0
for fr in asm.pop_ready():
    print(fr.stamp_ns, fr.axes[0].error)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.splitlines()
    assert lines[0] == "7 lost frame(s) 1 of 1000000000 (a later frame arrived first)"
    assert lines[1] == "8 lost frame(s) 0-999999997 of 1000000000 (a later frame arrived first)"
    # with the receiver's limit the count itself is refused
    asm = PartitionAssembler(max_count=257, timeout_s=1, clock=lambda: 0.0)
    asm.expect(9, {"tz": 3})
    asm.add_frame(9, "tz", 0, 1_000_000_000, np.zeros(3))
    (fr,) = asm.pop_ready()
    assert "more than max_partitions 257" in fr.axes[0].error


def test_the_assembler_holds_at_most_max_bytes_per_axis():
    asm = PartitionAssembler(max_bytes=1000, timeout_s=10, clock=lambda: 0.0)
    asm.expect(1, {"tz": 5, "tx": 2})
    for i in range(2):
        asm.add_frame(1, "tx", i, 2, np.zeros(100, np.uint8))
    for i in range(5):
        asm.add_frame(1, "tz", i, 5, np.zeros(400, np.uint8))   # the third frame passes 1000 bytes
    assert asm.held_bytes() == 200     # tz's frames are freed once it failed
    asm.add_bounds(1, "tx", 2, "b")
    (fr,) = asm.pop_ready()
    tx, tz = fr.axes[1], fr.axes[0]
    assert tz.axis == "tz" and "max_memory_mb" in tz.error and "at frame 2 of 5" in tz.error
    assert tx.ok


# ---- input-side refusals (ROS-free) ----

def _cloud_msg(points, dtype="<f4"):
    """A PointCloud2 of x, y, z float32 (or float64) points, written here byte by byte."""
    pts = np.asarray(points, dtype=dtype)
    size = pts.dtype.itemsize
    fields = [T.PointField(name=n, offset=i * size, datatype=7 if size == 4 else 8, count=1) for i, n in enumerate("xyz")]
    return T.PointCloud2(header=msgbuild.make_header(T, 5, "cam"), height=1, width=len(pts), fields=fields, is_bigendian=False,
                         point_step=3 * size, row_step=3 * size * len(pts), data=np.frombuffer(pts.tobytes(), np.uint8).copy(),
                         is_dense=True)


@pytest.mark.parametrize("dtype", ["<f4", "<f8"])
def test_a_wrong_is_bigendian_flag_is_a_clear_error(dtype):
    from pws_ros.bridge import cloudconv

    pts = np.random.default_rng(1).uniform([-1, -1, 0.5], [1, 1, 4], (200, 3))
    msg = _cloud_msg(pts, dtype)
    np.testing.assert_allclose(cloudconv.cloud_from_pointcloud2(msg)[0].points, pts, rtol=1e-6)
    msg.is_bigendian = True   # the live case: little-endian floats flagged big-endian (z ~ 4.6e-41 m)
    with pytest.raises(PwsError, match="is_bigendian=True, but its x, y, z read big-endian are implausible"):
        cloudconv.cloud_from_pointcloud2(msg)
    # honest big-endian data is read as before
    big = _cloud_msg(pts, dtype)
    big.data = np.frombuffer(pts.astype(dtype.replace("<", ">")).tobytes(), np.uint8).copy()
    big.is_bigendian = True
    np.testing.assert_allclose(cloudconv.cloud_from_pointcloud2(big)[0].points, pts, rtol=1e-6)
    # a cloud of mostly NaN (an organized cloud's holes) is no evidence either way
    holes = pts.copy()
    holes[: 150] = np.nan
    assert len(cloudconv.cloud_from_pointcloud2(_cloud_msg(holes, dtype))[0]) == 50


def test_camera_info_with_nan_coefficients_is_refused_and_unknown_models_are_named():
    from pws_ros.core.camera import CameraIntrinsics

    cam = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5, "cam")
    info = msgbuild.camera_info_from_intrinsics(msgbuild.make_header(T, 1, "cam"), cam, T)
    assert msgconv.intrinsics_from_camera_info(info) == cam and msgconv.distortion_note(info) == ""
    info.distortion_model = "kannala_brandt_x"
    assert "'kannala_brandt_x' is not one of plumb_bob, rational_polynomial, equidistant" in msgconv.distortion_note(info)
    assert "rectified (pinhole" in msgconv.distortion_note(info)
    info.distortion_model = "plumb_bob"
    info.d = np.array([0.1, 0.0, 0.0, 0.0, 0.0])
    assert "non-zero plumb_bob distortion coefficients" in msgconv.distortion_note(info)
    for field, index, value in (("d", 0, math.nan), ("d", 4, math.inf), ("k", 2, math.nan)):
        bad = msgbuild.camera_info_from_intrinsics(msgbuild.make_header(T, 1, "cam"), cam, T)
        arr = np.array(getattr(bad, field), dtype=np.float64) if len(getattr(bad, field)) else np.zeros(5)
        arr[index] = value
        setattr(bad, field, arr)
        with pytest.raises(PwsError, match=rf"CameraInfo {field.upper()}\[{index}\] is {value}"):
            msgconv.intrinsics_from_camera_info(bad)
    huge = msgbuild.camera_info_from_intrinsics(msgbuild.make_header(T, 1, "cam"), cam, T)
    huge.width = 4_000_000_000
    with pytest.raises(PwsError, match="above 16384 px a side"):
        msgconv.intrinsics_from_camera_info(huge)


def test_a_malformed_cloud_first_does_not_lock_out_the_rgbd_camera(model_path):
    """``input_mode: auto`` uses the first source that completes a frame. A malformed PointCloud2 on the
    (unused) points topic before the camera's first frame used to lock the node onto PointCloud2 for
    good, every RGB-D frame then ignored in silence; now the failed frame is an ERROR certification
    and the camera's frames are certified after it (pipeline, and cloud_listener in the chain)."""
    from pws_ros.core.cloud import Cloud
    from pws_ros.nodes.pipeline import PipelineNode

    bad_stamp, good_stamp = T0, T0 + 100 * MS
    pts = np.stack(np.meshgrid(np.linspace(-0.5, 0.5, 32), np.linspace(-0.4, 0.4, 24)), -1).reshape(-1, 2)
    cloud = Cloud(np.column_stack([pts, np.full(len(pts), 2.0)]), np.full((len(pts), 3), 0.5))
    bad = msgbuild.cloud_to_pointcloud2(msgbuild.make_header(T, bad_stamp, "cam"), cloud, T, organized_shape=(24, 32))
    bad.point_step = 0                                   # malformed: no field fits
    for mode in ("pipeline", "four"):
        bus = Bus()
        extra = {"input_mode": "auto", "points_topic": "/cam/points"}
        if mode == "pipeline":
            ctx = Context(bus, "pipeline", **params(model_path, **extra))
            nodes, tick = [PipelineNode(ctx)], []
        else:
            ctxs, nodes = four_nodes(bus, model_path, **extra)
            tick = [ctxs["certifier"]]
        certs = bus.published["/certification"]
        try:
            bus.publish("/cam/points", bad)
            assert wait_for(lambda: len(certs) >= 1, 60, tick=tick), mode
            for topic, msg in frame_messages(good_stamp).items():
                bus.publish(topic, msg)
            assert wait_for(lambda: len(certs) >= 2, 60, tick=tick), f"{mode}: the RGB-D frame after the bad cloud was not certified"
            time.sleep(0.3)
            assert stamps_of(certs) == [bad_stamp, good_stamp] and not bus.errors, (mode, stamps_of(certs), bus.errors)
            first, second = (msgbuild.parse_certification(m) for m in certs)
            assert all(v["level"] == 2 and "point_step" in v["message"] for v in first.values()), first
            assert all(v["level"] in (0, 1) for v in second.values()), second
        finally:
            for nd in nodes:
                nd.close()
            bus.close()
