"""Issue 26: a ROS-free fuzz of every message kind the nodes take (hypothesis). Generated malformed
messages (each a valid message with one to three fields replaced by hostile values within the ROS
field types: sizes, steps, encodings, byte orders, truncated or padded data, NaN/inf numbers, odd
frame tags and labels, mutated plan JSON) go through the nodes' own subscription callbacks and worker
steps, with an in-memory context (rosbags messages; not a stand-in for rclpy, whose glue is tested by
test_nodes_rclpy.py where ROS 2 exists). Asserted for every example: no exception escapes a callback
(a worker step raises only PwsError, which the worker logs), the Python heap grows by at most
``MAX_HEAP`` while the example runs (tracemalloc; numpy's arrays count), and every frame ends in its
outcome: the cloud or a ``cloud/errors`` report (cloud_listener), frames and bounds or a
``rendered/errors`` report for every planned axis (projector), exactly one certification for every
input frame a message names (certifier)."""
from __future__ import annotations

import json
import math
import tracemalloc
from collections import Counter, defaultdict

import numpy as np
import pytest

import hypothesis  # noqa: E402  (a test dependency: never skipped)
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from pws_ros.bridge import cloudconv, msgbuild, msgconv, scheme  # noqa: E402
from pws_ros.bridge.config import config_from_params  # noqa: E402
from pws_ros.core.bounds import render_plan  # noqa: E402
from pws_ros.core.camera import CameraIntrinsics  # noqa: E402
from pws_ros.core.cloud import cloud_from_rgbd  # noqa: E402
from pws_ros.core.errors import PwsError  # noqa: E402
from pws_ros.core.partition import plan_partitions  # noqa: E402

T = msgbuild.rosbags_types()
T0 = 1_700_000_000_000_000_000
CAM = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5, "cam")
MAX_HEAP = 64 * 2**20
FUZZ = settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))

U32 = st.one_of(st.sampled_from([0, 1, 2, 3, 7, 24, 32, 33, 2**16, 2**31 - 1, 2**32 - 1]), st.integers(0, 2**32 - 1))
I32 = st.one_of(st.sampled_from([0, -1, -5, 1, 2**31 - 1, -(2**31)]), st.integers(-(2**31), 2**31 - 1))
FLOATS = st.one_of(st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -1.0, 1e300, 5e-324]), st.floats(allow_nan=True))
TEXT = st.one_of(st.sampled_from(["", "rgb8", "bgr8", "mono8", "16UC1", "32FC1", "32FC3", "rgba8", "8UC3", "yuv422", "16uc1"]),
                 st.text(max_size=12))


def header(stamp_ns, frame="cam"):
    return msgbuild.make_header(T, stamp_ns, frame)


# ---- valid messages of one input frame ----

def depth_msg(stamp, enc="16UC1"):
    mm = np.full((24, 32), 2000, np.uint16)
    mm[6:18, 8:20] = 1200
    arr = mm if enc == "16UC1" else (mm / 1000.0).astype(np.float32)
    return msgbuild.image_from_numpy(header(stamp), arr, T)


def color_msg(stamp):
    rgb = np.random.default_rng(3).integers(0, 256, (24, 32, 3), dtype=np.uint8)
    return msgbuild.image_from_numpy(header(stamp), rgb, T)


def info_msg(stamp):
    return msgbuild.camera_info_from_intrinsics(header(stamp), CAM, T)


def points_msg(stamp, organized=True):
    cloud = cloud_from_rgbd(np.where(np.arange(32)[None, :] < 16, 1.2, 2.0) * np.ones((24, 1)),
                            np.full((24, 32, 3), 128, np.uint8), CAM)
    return msgbuild.cloud_to_pointcloud2(header(stamp), cloud, T, organized_shape=(24, 32) if organized else None)


def _bytes_mutation(data, choice, n):
    data = np.asarray(data, dtype=np.uint8)
    if choice == "truncate":
        return data[: n % (len(data) + 1)].copy()
    if choice == "extend":
        return np.concatenate([data, np.full(n % 4096, 0xFF, np.uint8)])
    if choice == "empty":
        return np.zeros(0, np.uint8)
    out = data.copy()
    if len(out):
        out[n % len(out)] ^= 0xFF
    return out


@st.composite
def mutated(draw, msg, kind):
    """``msg`` with one to three fields replaced by hostile values (each within its ROS type)."""
    for _ in range(draw(st.integers(1, 3))):
        if kind == "image":
            f = draw(st.sampled_from(["width", "height", "step", "encoding", "is_bigendian", "data", "stamp"]))
        elif kind == "info":
            f = draw(st.sampled_from(["width", "height", "k", "d", "distortion_model", "binning_x", "roi", "stamp"]))
        else:
            f = draw(st.sampled_from(["width", "height", "point_step", "row_step", "is_bigendian", "data", "fields", "stamp"]))
        if f in ("width", "height", "step", "point_step", "row_step", "binning_x"):
            setattr(msg, f, draw(U32))
        elif f == "encoding":
            msg.encoding = draw(TEXT)
        elif f == "distortion_model":
            msg.distortion_model = draw(TEXT)
        elif f == "is_bigendian":
            msg.is_bigendian = not msg.is_bigendian
        elif f == "data":
            msg.data = _bytes_mutation(msg.data, draw(st.sampled_from(["truncate", "extend", "empty", "flip"])), draw(st.integers(0, 10**6)))
        elif f == "stamp":
            msg.header.stamp = T.Time(sec=draw(I32), nanosec=draw(st.integers(0, 999_999_999)))
        elif f in ("k", "d"):
            arr = np.array(getattr(msg, f), dtype=np.float64).reshape(-1) if len(getattr(msg, f)) else np.zeros(5)
            if draw(st.booleans()) or not len(arr):
                arr = np.array(draw(st.lists(FLOATS, max_size=14)), dtype=np.float64)
            else:
                arr[draw(st.integers(0, len(arr) - 1))] = draw(FLOATS)
            setattr(msg, f, arr)
        elif f == "roi":
            msg.roi.width, msg.roi.height = draw(U32), draw(U32)
        elif f == "fields":
            fields = list(msg.fields)
            i = draw(st.integers(0, len(fields) - 1))
            g = fields[i]
            choice = draw(st.sampled_from(["offset", "datatype", "name", "count", "drop"]))
            if choice == "drop":
                fields.pop(i)
            else:
                kw = {"name": g.name, "offset": g.offset, "datatype": g.datatype, "count": g.count}
                kw[choice] = {"offset": draw(U32), "datatype": draw(st.integers(0, 255)), "name": draw(TEXT),
                              "count": draw(U32)}[choice]
                fields[i] = T.PointField(**kw)
            msg.fields = fields
    return msg


class SyncContext:
    """The NodeContext interface, synchronous: publications are recorded, callbacks are called by the test."""

    def __init__(self, name, **params):
        self.name, self.types = name, T
        self.config = config_from_params(params)
        self.on_change = None
        self.qos_events = 0
        self.logs = []
        self.subs = defaultdict(list)
        self.published = defaultdict(list)

    def log(self, level, message):
        self.logs.append((level, message))

    def now_ns(self):
        return T0

    def resolve(self, topic):
        return topic if topic.startswith("/") else "/" + topic

    def publisher(self, msg_type, topic, *, kind=None, depth=None):
        sink = self.published[self.resolve(topic)]
        return type("Pub", (), {"publish": staticmethod(sink.append)})()

    def subscription(self, msg_type, topic, callback, *, kind=None, depth=None):
        self.subs[self.resolve(topic)].append(callback)

    def timer(self, period, callback):
        return callback

    def deliver(self, topic, msg):
        for cb in self.subs[topic]:
            cb(msg)   # a callback must never raise: an exception here fails the example


def bounded(fn):
    """Run ``fn`` with tracemalloc and assert its peak heap growth stays under MAX_HEAP."""
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        fn()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak - base < MAX_HEAP, f"{(peak - base) / 2**20:.0f} MiB allocated"


def run_worker_step(fn, item):
    """What a node's Worker does with an item: only PwsError may come out (it becomes a WARN)."""
    try:
        fn(item)
    except PwsError:
        pass


INPUT_PARAMS = {"model_path": "unused.pt", "axes": ["tx", "tz"], "input_mode": "auto", "depth_topic": "/cam/depth",
                "color_topic": "/cam/color", "camera_info_topic": "/cam/info", "points_topic": "/cam/points",
                "depth_camera_info_topic": ""}


def input_case():
    """One to four input messages (PointCloud2, depth/colour Image, CameraInfo) of nearby stamps, mutated or not."""
    def one(kind, stamp, bad):
        base = {"points": lambda: points_msg(stamp, bad % 2 == 0), "depth": lambda: depth_msg(stamp, ["16UC1", "32FC1"][bad % 2]),
                "color": lambda: color_msg(stamp), "info": lambda: info_msg(stamp)}[kind]()
        k = {"points": "cloud", "info": "info"}.get(kind, "image")
        return st.just(base) if bad == 0 else mutated(base, k)

    msg = st.tuples(st.sampled_from(["points", "depth", "color", "info"]), st.sampled_from([T0, T0 + 1_000_000]),
                    st.integers(0, 3)).flatmap(lambda t: one(*t).map(lambda m: (t[0], m)))
    return st.lists(msg, min_size=1, max_size=4)


TOPICS = {"points": "/cam/points", "depth": "/cam/depth", "color": "/cam/color", "info": "/cam/info"}


@FUZZ
@given(input_case())
def test_fuzz_camera_inputs_through_cloud_listener(messages):
    from pws_ros.nodes.cloud_listener import CloudListenerNode

    ctx = SyncContext("cloud_listener", **INPUT_PARAMS)
    node = CloudListenerNode(ctx)
    raws = []
    node.frontend.on_frame = raws.append
    try:
        def run():
            for kind, msg in messages:
                ctx.deliver(TOPICS[kind], msg)
            for raw in raws:
                run_worker_step(node._process, raw)
        bounded(run)
        # every input frame that was assembled ends in its cloud or in a cloud/errors report (-> its ERROR certification)
        clouds = [msgconv.header_stamp_ns(m) for m in ctx.published["/cloud"]]
        errors = [scheme.parse_input_error(m)[0] for m in ctx.published["/cloud/errors"]]
        assert sorted(clouds + errors) == sorted(r.stamp_ns for r in raws)
        for m in ctx.published["/cloud"]:   # what goes on is a cloud the planner can read
            assert len(cloudconv.cloud_from_pointcloud2(m)[0]) > 0
    finally:
        node.close()


# ---- the four-process scheme ----

@pytest.fixture(scope="module")
def chain_messages():
    """The real plan, frames and bounds of one frame (tiny scene), to mutate."""
    depth = np.full((24, 32), 2.0)
    depth[6:18, 8:20] = 1.2
    cloud = cloud_from_rgbd(depth, np.random.default_rng(0).integers(0, 256, (24, 32, 3), dtype=np.uint8), CAM)
    plan = plan_partitions(cloud, CAM, "tz", 0.01, "pws_of")
    rp = render_plan(cloud, CAM, plan)
    bundle = scheme.PlanBundle(T0, "cam", "pws_of", CAM, ["tz"], {"tz": plan}, {})
    n = len(plan.alphas)
    return {"plan": scheme.plan_bundle_to_json(bundle), "frames": [scheme.frame_message(T0, "tz", i, n, rp.frames[i], T) for i in range(n)],
            "bounds": scheme.bounds_message(T0, "tz", rp, T), "cloud": msgbuild.cloud_to_pointcloud2(header(T0), cloud, T), "n": n}


JSON_VALUES = st.recursive(st.one_of(st.none(), st.booleans(), st.integers(-2**70, 2**70), st.floats(allow_nan=False),
                                     st.text(max_size=8), st.sampled_from(["tz", "ry", "NaN", "x", T0])),
                           lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
                           max_leaves=6)


@st.composite
def plan_text(draw, text):
    d = json.loads(text)
    for _ in range(draw(st.integers(1, 3))):
        path = draw(st.sampled_from(["stamp_ns", "axes", "camera", "method", "frame_id", "imaging", "errors",
                                     "plans.tz.alphas", "plans.tz.axis", "plans.tz.num_partitions", "camera.width", "plans.tz"]))
        *parents, key = path.split(".")
        node = d
        for p in parents:
            node = node.get(p) if isinstance(node, dict) else None
        if isinstance(node, dict):
            node[key] = draw(st.one_of(JSON_VALUES, st.just(float("nan")), st.just(5)))
    return json.dumps(d)


def tag_text():
    return st.one_of(
        st.tuples(st.sampled_from([T0, T0 + 1, -5_000_000_000]), st.sampled_from(["tz", "tx", "yaw"]), st.integers(-2, 40),
                  st.sampled_from([1, 2, 17, 999_999_999 + 1, 0])).map(lambda t: "/".join(map(str, t))),
        st.text(max_size=30))


@st.composite
def scheme_case(draw, base):
    out = []
    for _ in range(draw(st.integers(1, 8))):
        kind = draw(st.sampled_from(["plan", "frame", "bounds", "error"]))
        bad = draw(st.booleans())
        if kind == "plan":
            out.append(("/plan", T.String(data=draw(plan_text(base["plan"])) if bad else base["plan"])))
        elif kind == "frame":
            src = base["frames"][draw(st.integers(0, base["n"] - 1))]
            msg = T.Image(header=header(T0, src.header.frame_id), height=src.height, width=src.width, encoding=src.encoding,
                          is_bigendian=src.is_bigendian, step=src.step, data=src.data.copy())
            if bad:
                msg = draw(mutated(msg, "image"))
                if draw(st.booleans()):
                    msg.header.frame_id = draw(tag_text())
            out.append(("/rendered/frames", msg))
        elif kind == "bounds":
            src = base["bounds"]
            dims = [T.MultiArrayDimension(label=d.label, size=d.size, stride=d.stride) for d in src.layout.dim]
            data = np.array(src.data, dtype=np.float64)
            if bad:
                what = draw(st.sampled_from(["label", "size", "data", "value"]))
                i = draw(st.integers(0, 2))
                if what == "label":
                    dims[i] = T.MultiArrayDimension(label=draw(st.one_of(tag_text().map(lambda s: "pws_bounds/" + s), TEXT)),
                                                    size=dims[i].size, stride=dims[i].stride)
                elif what == "size":
                    dims[i] = T.MultiArrayDimension(label=dims[i].label, size=draw(U32), stride=dims[i].stride)
                elif what == "data":
                    data = data[: draw(st.integers(0, len(data)))]
                elif len(data):
                    data[draw(st.integers(-len(data), len(data) - 1))] = draw(FLOATS)
            out.append(("/rendered/bounds", T.Float64MultiArray(layout=T.MultiArrayLayout(dim=dims, data_offset=0), data=data)))
        else:
            d = {"format": scheme.RENDER_ERROR_FORMAT, "stamp_ns": T0, "axis": "tz", "reason": "x"}
            if bad:
                d[draw(st.sampled_from(list(d)))] = draw(JSON_VALUES)
            out.append(("/rendered/errors", T.String(data=json.dumps(d))))
    return out


def named_stamp(topic, msg):
    """The input frame a message names (None when it names none validly)."""
    if topic == "/plan":
        try:
            bundle = scheme.plan_bundle_from_json(msg.data, 257)
        except PwsError:
            return scheme.plan_bundle_stamp(msg.data)
        return None if bundle.plans else bundle.stamp_ns   # a valid plan opens its set once data flows
    if topic == "/rendered/frames":
        owner = scheme.tag_owner(msg.header.frame_id)
    elif topic == "/rendered/bounds":
        owner = scheme.tag_owner(msg.layout.dim[0].label) if len(msg.layout.dim) else None
    else:
        try:
            return scheme.parse_render_error(msg)[0]
        except PwsError:
            return None
    return owner[0] if owner else None


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    from conftest import MeanThresholdNet
    from pws_ros.core.model import save_model

    return save_model(MeanThresholdNet(0.5), tmp_path_factory.mktemp("fuzz") / "model.pt", ["c0", "c1"], input_size=(24, 32))


def test_fuzz_four_process_scheme_through_the_certifier(chain_messages, model_file):
    from pws_ros.nodes.certifier import CertifierNode

    params = {"model_path": str(model_file), "axes": ["tz"], "n0": 8, "n": 16, "imaging": "paper"}

    @FUZZ
    @given(scheme_case(chain_messages))
    def check(messages):
        ctx = SyncContext("certifier", **params)
        node = CertifierNode(ctx)
        frames = []
        node.worker.submit = frames.append
        try:
            def run():
                for topic, msg in messages:
                    ctx.deliver(topic, msg)
                node._poll()
                node.assembler._clock = lambda: float("inf")   # every set still pending times out now
                node._poll()
                for fr in frames:
                    node._process(fr)
            bounded(run)
            certs = Counter(msgconv.header_stamp_ns(m) for m in ctx.published["/certification"])
            named = {s for s in (named_stamp(t, m) for t, m in messages) if s is not None}
            assert named <= set(certs), (named, certs)           # every named frame ends in a certification ...
            assert all(c <= 1 + node.assembler.time_jumps for c in certs.values()), certs   # ... exactly one per pass
            assert not node.assembler.pending() and node.assembler.held_bytes() == 0
        finally:
            node.close()

    check()


def test_fuzz_plan_and_plan_cloud_through_the_projector(chain_messages, monkeypatch):
    from pws_ros.nodes import projector

    monkeypatch.setattr(projector, "CLOUD_WAIT_S", 0.01)
    params = {"model_path": "unused.pt", "axes": ["tz"], "imaging": "paper", "publish_preview": False}

    @FUZZ
    @given(st.lists(st.one_of(
        st.booleans().flatmap(lambda bad: (plan_text(chain_messages["plan"]) if bad else st.just(chain_messages["plan"]))
                              .map(lambda s: ("/plan", T.String(data=s)))),
        st.booleans().flatmap(lambda bad: (mutated(msgbuild.cloud_to_pointcloud2(header(T0), cloudconv.cloud_from_pointcloud2(
            chain_messages["cloud"])[0], T), "cloud") if bad else st.just(chain_messages["cloud"])).map(lambda m: ("/plan/cloud", m)))),
        min_size=1, max_size=4))
    def check(messages):
        ctx = SyncContext("projector", **params)
        node = projector.ProjectorNode(ctx)
        bundles = []
        node.worker.submit = bundles.append
        try:
            def run():
                for topic, msg in messages:
                    ctx.deliver(topic, msg)
                for b in bundles:
                    run_worker_step(node._process, b)
            bounded(run)
            answered = Counter([(b.stamp_ns, b.axis) for b in map(scheme.parse_bounds_message, ctx.published["/rendered/bounds"])]
                               + [scheme.parse_render_error(m)[:2] for m in ctx.published["/rendered/errors"]])
            for b in bundles:   # every planned axis of every plan taken: frames and bounds, or a render error
                for axis in b.plans:
                    assert answered[(b.stamp_ns, axis)] >= 1, (b.stamp_ns, axis)
        finally:
            node.close()

    check()
