"""Issue 26, live: both launch files (``pws.launch.py``: one ``pipeline``; ``pws_nodes.launch.py``: the
four nodes) run as real ROS 2 processes, a graph flooded with malformed messages on every input topic
and every internal topic of the four-process scheme, then the valid demo recording.

Asserted for each launch: no node process dies, the log holds no traceback, the peak RSS (VmHWM) of
every node stays under ``max_memory_mb`` plus its baseline (taken after one valid warm-up frame,
before the flood), and the demo frames played afterwards get >= 3 certifications (not ERROR) with the
documented key schema. Needs rclpy, launch and launch_ros (ROS 2 Jazzy sourced): skipped otherwise.

Three runs: the shipped ``input_mode: auto`` with each launch file (the warm-up frame locks it onto RGB-D,
so the PointCloud2 cases are then ignored and counted), and the four nodes with ``input_mode: pointcloud2``
(the demo played as the organized cloud a driver publishes; the RGB-D cases are then the ignored ones).
The nodes run from this working tree and DDS stays on the loopback interface (a unique
``ROS_DOMAIN_ID``, Cyclone DDS on ``lo`` without multicast): :mod:`pws_ros.nodes.live`.

``PWS_FLOOD_REPORT=<dir>`` writes ``<launch>-<input_mode>.json`` (cases, peak memory, log lines) and the log there.
"""
from __future__ import annotations

import json
import math
import os
import re
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from conftest import need_ros
from pws_ros.nodes.live import (  # imports without ROS: rclpy only inside its functions
    COLOR, DEPTH, DEPTH_INFO, INFO, POINTS, REPO, TF_STATIC, Launch, Player, demo_frames, play_frame, ros_env, status_kb, wait_for,
)

pytestmark = [pytest.mark.rclpy, pytest.mark.slow]

LAUNCHES = {"pws.launch.py": ("pipeline",), "pws_nodes.launch.py": ("cloud_listener", "partition_planner", "projector", "certifier")}
MAX_MEMORY_MB = 512.0
INTERNAL = {"/cloud": "PointCloud2", "/cloud/camera_info": "CameraInfo", "/cloud/errors": "String", "/plan": "String",
            "/plan/cloud": "PointCloud2", "/rendered/frames": "Image", "/rendered/bounds": "Float64MultiArray",
            "/rendered/errors": "String"}
INPUTS = {DEPTH: "Image", COLOR: "Image", INFO: "CameraInfo", DEPTH_INFO: "CameraInfo", POINTS: "PointCloud2"}
DEMO_CERTIFICATIONS = 3
W, H, FX, CX, CY = 160, 120, 115.0, 79.5, 59.5   # the flood's camera: the demo model's input (160x90) fits in it


def write_config(path: Path, input_mode: str) -> Path:
    path.write_text("/**:\n  ros__parameters:\n" + "".join(f"    {k}: {v}\n" for k, v in {
        "input_mode": input_mode,
        "model_path": json.dumps(str(REPO / "bags" / "models" / "classifier_sigma0.50.pt")),
        "axes": "[tz, ry]", "n0": 16, "n": 32, "max_memory_mb": MAX_MEMORY_MB, "input_qos": "reliable",
        "input_qos_depth": 10, "health_period_s": 1.0, "assembly_timeout_s": 20.0, "max_partitions": 129,
    }.items()))
    return path


# ---- messages -----------------------------------------------------------------------------------

class Msgs:
    """Valid and malformed messages (rclpy types) of a small 160x120 camera, and of the four-process scheme."""

    def __init__(self, T):
        from pws_ros.bridge import msgbuild
        from pws_ros.core.camera import CameraIntrinsics

        self.T, self.mb = T, msgbuild
        self.cam = CameraIntrinsics(W, H, FX, FX, CX, CY, "flood_cam")

    def header(self, stamp, frame="flood_cam"):
        return self.mb.make_header(self.T, stamp, frame)

    def depth(self, stamp, frame="flood_cam", mm=None):
        if mm is None:
            mm = np.full((H, W), 2000, np.uint16)
            mm[H // 4: 3 * H // 4, W // 4: W // 2] = 1200
        return self.mb.image_from_numpy(self.header(stamp, frame), mm, self.T)

    def depth32(self, stamp, values):
        return self.mb.image_from_numpy(self.header(stamp), np.asarray(values, np.float32), self.T)

    def color(self, stamp, frame="flood_cam", shape=(H, W)):
        rgb = np.random.default_rng(stamp % 997).integers(0, 256, (*shape, 3), dtype=np.uint8)
        return self.mb.image_from_numpy(self.header(stamp, frame), rgb, self.T)

    def info(self, stamp, frame="flood_cam", cam=None):
        return self.mb.camera_info_from_intrinsics(self.header(stamp, frame), cam or self.cam, self.T)

    def points(self, stamp):
        from pws_ros.core.cloud import cloud_from_rgbd

        cloud = cloud_from_rgbd(np.where(np.arange(W)[None, :] < W // 2, 1.2, 2.0) * np.ones((H, 1)),
                                np.full((H, W, 3), 128, np.uint8), self.cam)
        return self.mb.cloud_to_pointcloud2(self.header(stamp), cloud, self.T, organized_shape=(H, W))

    def frame(self, stamp, **changes):
        """(info, depth info, depth, colour) of one input frame (a registered camera: the depth stream's
        CameraInfo is the colour camera's); ``changes`` = {"depth": fn(msg) ...} corrupt one of them."""
        out = {INFO: self.info(stamp), DEPTH_INFO: self.info(stamp), DEPTH: self.depth(stamp), COLOR: self.color(stamp)}
        for key, fn in changes.items():
            topic = {"info": INFO, "depth_info": DEPTH_INFO, "depth": DEPTH, "color": COLOR}[key]
            out[topic] = fn(out[topic])
        return list(out.items())

    def chain(self, stamp):
        """The real plan, frames, bounds and cloud of one tiny frame (axis tz), to corrupt."""
        from pws_ros.bridge import scheme
        from pws_ros.core.bounds import render_plan
        from pws_ros.core.cloud import cloud_from_rgbd
        from pws_ros.core.partition import plan_partitions

        depth = np.full((H, W), 2.0)
        depth[H // 4: 3 * H // 4, W // 4: W // 2] = 1.2
        cloud = cloud_from_rgbd(depth, np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8), self.cam)
        plan = plan_partitions(cloud, self.cam, "tz", 0.01, "pws_of")
        rp = render_plan(cloud, self.cam, plan)
        n = len(plan.alphas)
        bundle = scheme.PlanBundle(stamp, "flood_cam", "pws_of", self.cam, ["tz"], {"tz": plan}, {})
        return {"plan": json.loads(scheme.plan_bundle_to_json(bundle)), "n": n, "rp": rp, "cloud": cloud,
                "frame": lambda i, count=n, tag=None: self._tagged(scheme.frame_message(stamp, "tz", i, count, rp.frames[i], self.T), tag),
                "bounds": lambda: scheme.bounds_message(stamp, "tz", rp, self.T)}

    @staticmethod
    def _tagged(msg, tag):
        if tag is not None:
            msg.header.frame_id = tag
        return msg


def set_(msg, **fields):
    for k, v in fields.items():
        setattr(msg, k, v)
    return msg


def flood_cases(M, base: int) -> list[tuple[str, list[tuple[str, object]]]]:
    """The malformed cases: (name, [(topic, message), ...]); each input case has its own stamp."""
    T = M.T
    s = iter(range(base, base + 10**12, 10_000_000))   # 10 ms apart
    u8 = T.u8
    cases: list[tuple[str, list]] = []

    def add(name, msgs):
        cases.append((name, msgs))

    def frame(name, **changes):
        add(name, M.frame(next(s), **changes))

    # depth image
    frame("depth encoding yuv422", depth=lambda m: set_(m, encoding="yuv422"))
    frame("depth encoding empty", depth=lambda m: set_(m, encoding=""))
    frame("depth encoding 32FC3", depth=lambda m: set_(m, encoding="32FC3"))
    frame("depth data truncated", depth=lambda m: set_(m, data=u8(np.asarray(m.data)[: len(m.data) // 2])))
    frame("depth data empty", depth=lambda m: set_(m, data=u8(np.zeros(0, np.uint8))))
    frame("depth 0x0", depth=lambda m: set_(m, width=0, height=0))
    frame("depth declares 65535x65535", depth=lambda m: set_(m, width=65535, height=65535, step=131070))
    frame("depth declares 2^32-1 rows", depth=lambda m: set_(m, height=2**32 - 1))
    frame("depth step 1", depth=lambda m: set_(m, step=1))
    frame("depth step 2^32-1", depth=lambda m: set_(m, step=2**32 - 1))
    frame("depth is_bigendian flipped", depth=lambda m: set_(m, is_bigendian=1))
    frame("depth data padded by 1 MB", depth=lambda m: set_(m, data=u8(np.concatenate([np.asarray(m.data), np.full(2**20, 255, np.uint8)]))))
    frame("depth all zero", depth=lambda m: set_(M.depth(0, mm=np.zeros((H, W), np.uint16)), header=m.header))
    frame("depth one valid pixel", depth=lambda m: set_(M.depth(0, mm=np.pad(np.full((1, 1), 1500, np.uint16), ((H // 2, H - H // 2 - 1), (W // 2, W - W // 2 - 1)))),
                                                        header=m.header))
    for name, val in (("NaN", math.nan), ("inf", math.inf), ("negative", -1.0), ("1e30", 1e30)):
        frame(f"depth 32FC1 all {name}", depth=lambda m, v=val: set_(M.depth32(0, np.full((H, W), v)), header=m.header))
    frame("depth size differs from colour", depth=lambda m: set_(M.depth(0, mm=np.full((H, W + 8), 2000, np.uint16)), header=m.header))
    frame("depth frame id differs", depth=lambda m: set_(m, header=set_(m.header, frame_id="other_frame")))
    # colour image
    frame("colour encoding bayer_rggb8", color=lambda m: set_(m, encoding="bayer_rggb8"))
    frame("colour encoding 16UC1", color=lambda m: set_(m, encoding="16UC1"))
    frame("colour encoding rgba8 on rgb8 data", color=lambda m: set_(m, encoding="rgba8"))
    frame("colour data truncated", color=lambda m: set_(m, data=u8(np.asarray(m.data)[:100])))
    frame("colour data empty", color=lambda m: set_(m, data=u8(np.zeros(0, np.uint8))))
    frame("colour declares 100000x100000", color=lambda m: set_(m, width=100000, height=100000, step=300000))
    frame("colour step 0", color=lambda m: set_(m, step=0))
    frame("colour 1 px narrower (step mismatch)", color=lambda m: set_(m, width=W - 1))
    frame("colour is_bigendian", color=lambda m: set_(m, is_bigendian=1))
    frame("colour 8 px wider (not registered)", color=lambda m: set_(M.color(0, shape=(H, W + 8)), header=m.header))
    # CameraInfo
    frame("info K zero", info=lambda m: set_(m, k=np.zeros(9)))
    frame("info fx NaN", info=lambda m: set_(m, k=np.array([math.nan, 0, CX, 0, FX, CY, 0, 0, 1.0])))
    frame("info fy inf", info=lambda m: set_(m, k=np.array([FX, 0, CX, 0, math.inf, CY, 0, 0, 1.0])))
    frame("info fx negative", info=lambda m: set_(m, k=np.array([-FX, 0, CX, 0, FX, CY, 0, 0, 1.0])))
    frame("info 0x0", info=lambda m: set_(m, width=0, height=0))
    frame("info 100000x100000", info=lambda m: set_(m, width=100000, height=100000))
    frame("info D NaN, unknown model", info=lambda m: set_(m, distortion_model="fisheye_unknown", d=[math.nan, 0.0, 0.0, 0.0, 0.0]))
    frame("info D 10000 coefficients", info=lambda m: set_(m, d=[0.1] * 10000))
    frame("info binning 2^32-1", info=lambda m: set_(m, binning_x=2**32 - 1, binning_y=2**32 - 1))
    frame("info roi beyond the image", info=lambda m: (set_(m.roi, x_offset=10**6, width=10**6, height=10**6), m)[1])
    frame("info cx far outside", info=lambda m: set_(m, k=np.array([FX, 0, 1e9, 0, FX, CY, 0, 0, 1.0])))
    # depth CameraInfo (the auto depth_camera_info_topic)
    frame("depth info NaN", depth_info=lambda m: set_(m, k=np.full(9, math.nan)))
    frame("depth info of another camera", depth_info=lambda m: set_(m, k=np.array([2 * FX, 0, CX, 0, 2 * FX, CY, 0, 0, 1.0])))
    # stamps
    add("stamp zero", M.frame(0))
    add("stamp negative (-5 s)", M.frame(-5_000_000_000))
    add("stamp in 2038", M.frame((2**31 - 2) * 10**9))
    add("stamp back to the past", M.frame(base - 3_600 * 10**9))
    b = next(s)
    add("stamp repeated", M.frame(b) + M.frame(b))
    t1 = next(s)
    add("depth and colour 1 s apart", [(INFO, M.info(t1)), (DEPTH_INFO, M.info(t1)), (DEPTH, M.depth(t1)), (COLOR, M.color(t1 + 10**9))])
    t2 = next(s)
    add("depth and colour 0.15 s apart", [(INFO, M.info(t2)), (DEPTH_INFO, M.info(t2)), (DEPTH, M.depth(t2)),
                                          (COLOR, M.color(t2 + 150_000_000))])
    t3 = next(s)
    add("nanosec 2^32-1", [(t, set_(m, header=set_(m.header, stamp=T.Time(sec=int(t3 // 10**9), nanosec=2**32 - 1))))
                           for t, m in M.frame(t3)])
    add("burst: 30 depth images, no colour", [(DEPTH, M.depth(next(s))) for _ in range(30)])
    # PointCloud2
    pts = M.points

    def pc(name, fn):
        add(name, [(POINTS, fn(pts(next(s))))])

    pc("points is_bigendian on little-endian floats", lambda m: set_(m, is_bigendian=True))
    pc("points width 0", lambda m: set_(m, width=0, row_step=0, data=u8(np.zeros(0, np.uint8))))
    pc("points data truncated", lambda m: set_(m, data=u8(np.asarray(m.data)[:1000])))
    pc("points point_step 0", lambda m: set_(m, point_step=0))
    pc("points without x", lambda m: set_(m, fields=[f for f in m.fields if f.name != "x"]))
    pc("points field offset beyond point_step", lambda m: set_(m, fields=[set_(f, offset=10**6) if f.name == "z" else f for f in m.fields]))
    pc("points declare 2^32-1 x 2^32-1", lambda m: set_(m, width=2**32 - 1, height=2**32 - 1))
    pc("points all NaN", lambda m: set_(m, data=u8(np.frombuffer(np.full(len(m.data) // 4, np.nan, np.float32).tobytes(), np.uint8))))
    pc("points all at the origin", lambda m: set_(m, data=u8(np.zeros(len(m.data), np.uint8))))
    pc("points row_step 1", lambda m: set_(m, row_step=1))
    pc("points field datatype 99", lambda m: set_(m, fields=[set_(f, datatype=99) for f in m.fields]))
    pc("points field count 0", lambda m: set_(m, fields=[set_(f, count=0) for f in m.fields]))
    # /tf_static
    def tf(name, **kw):
        from geometry_msgs.msg import TransformStamped

        t = TransformStamped()
        t.header.frame_id, t.child_frame_id = kw.pop("parent", "camera_link"), kw.pop("child", "flood_cam")
        t.transform.rotation.w = 1.0
        for k, v in kw.items():
            obj, attr = k.split("_")
            setattr(getattr(t.transform, obj), attr, v)
        add(name, [(TF_STATIC, T.TFMessage(transforms=[t]))])

    tf("tf_static NaN rotation", rotation_w=math.nan)
    tf("tf_static zero quaternion", rotation_w=0.0)
    tf("tf_static empty frame ids", parent="", child="")
    tf("tf_static translation 1e300", translation_x=1e300)
    tf("tf_static frame is its own parent", parent="flood_cam", child="flood_cam")

    # ---- internal topics of the four-process scheme ----
    from pws_ros.bridge import scheme

    S = next(s)
    ch = M.chain(S)
    n = ch["n"]

    def plan(name, mutate):
        d = json.loads(json.dumps(ch["plan"]))
        d["stamp_ns"] = next(s)
        text = mutate(d)
        add(name, [("/plan", T.String(data=text if isinstance(text, str) else json.dumps(d)))])

    plan("plan axes 5", lambda d: d.__setitem__("axes", 5))
    plan("plan stamp_ns 'x'", lambda d: d.__setitem__("stamp_ns", "x"))
    plan("plan not JSON", lambda d: "{not json")
    plan("plan empty", lambda d: "")
    plan("plan JSON list", lambda d: "[1, 2, 3]")
    plan("plan nested 10000 deep", lambda d: "[" * 10000 + "]" * 10000)
    plan("plan unknown method", lambda d: d.__setitem__("method", "magic"))
    plan("plan camera 1e9 x 1e9", lambda d: d["camera"].update(width=10**9, height=10**9))
    plan("plan camera fx NaN (string)", lambda d: d["camera"].update(fx="NaN"))
    plan("plan 10^6 alphas", lambda d: d["plans"]["tz"].update(alphas=[0.0] * 10**6, num_partitions=10**6))
    plan("plan num_partitions 10^9", lambda d: d["plans"]["tz"].update(num_partitions=10**9))
    plan("plan alphas NaN (string)", lambda d: d["plans"]["tz"].update(alphas=["NaN"] * 3))
    plan("plan axes of 7 unknown axes", lambda d: d.__setitem__("axes", ["q1", "q2", "q3", "q4", "q5", "q6", "q7"]))
    plan("plan with no plans", lambda d: d.__setitem__("plans", {}))
    plan("plan errors not a dict", lambda d: d.__setitem__("errors", [1, 2]))
    S2 = next(s)
    add("frame tag with a billion frames", [("/rendered/frames", ch["frame"](0, tag=f"{S}/tz/999999999/1000000000"))])
    add("frame tag garbage", [("/rendered/frames", ch["frame"](0, tag="abc"))])
    add("frame tag negative index", [("/rendered/frames", ch["frame"](0, tag=f"{S2}/tz/-1/{n}"))])
    add("frame tag unknown axis", [("/rendered/frames", ch["frame"](0, tag=f"{S2}/yaw/0/{n}"))])
    add("frame 8UC1 encoding", [("/rendered/frames", set_(ch["frame"](1), encoding="8UC1"))])
    add("frame 1x1", [("/rendered/frames", set_(ch["frame"](n - 1), width=1, height=1, step=12))])
    add("frame data truncated", [("/rendered/frames", set_(ch["frame"](n - 1), data=u8(np.zeros(7, np.uint8))))])
    add("frame NaN pixels", [("/rendered/frames", set_(ch["frame"](0), data=u8(np.frombuffer(
        np.full(len(ch["frame"](0).data) // 4, np.nan, np.float32).tobytes(), np.uint8))))])
    add("frame duplicate index", [("/rendered/frames", ch["frame"](0)), ("/rendered/frames", ch["frame"](0))])
    add("frame declares 2^32-1 x 2^32-1", [("/rendered/frames", set_(ch["frame"](1), width=2**32 - 1, height=2**32 - 1))])

    def bounds(name, mutate):
        m = ch["bounds"]()
        mutate(m)
        add(name, [("/rendered/bounds", m)])

    def data_tail_nan(m):
        d = np.array(m.data, dtype=np.float64)
        d[-2:] = np.nan
        m.data = T.f64(d)

    bounds("bounds NaN shape", data_tail_nan)
    bounds("bounds label garbage", lambda m: setattr(m.layout.dim[0], "label", "garbage"))
    bounds("bounds label with a billion frames", lambda m: setattr(m.layout.dim[0], "label", f"pws_bounds/{S}/tz/1000000000"))
    bounds("bounds size 2^32-1", lambda m: setattr(m.layout.dim[1], "size", 2**32 - 1))
    bounds("bounds data empty", lambda m: setattr(m, "data", T.f64(np.zeros(0))))
    bounds("bounds all NaN", lambda m: setattr(m, "data", T.f64(np.full(len(m.data), np.nan))))
    bounds("bounds no dims", lambda m: setattr(m.layout, "dim", []))
    for name, text in (("render error not JSON", "nope"), ("render error without fields", json.dumps({"format": scheme.RENDER_ERROR_FORMAT})),
                       ("render error axis 5", json.dumps({"format": scheme.RENDER_ERROR_FORMAT, "stamp_ns": next(s), "axis": 5, "reason": "x"})),
                       ("render error for an unknown frame", json.dumps({"format": scheme.RENDER_ERROR_FORMAT, "stamp_ns": next(s), "axis": "tz", "reason": "forged"}))):
        add(name, [("/rendered/errors", T.String(data=text))])
    for name, text in (("input error not JSON", "}"), ("input error stamp 'x'", json.dumps({"format": scheme.INPUT_ERROR_FORMAT, "stamp_ns": "x", "reason": "r"})),
                       ("input error for an unknown frame", json.dumps({"format": scheme.INPUT_ERROR_FORMAT, "stamp_ns": next(s), "frame_id": "f", "reason": "forged"}))):
        add(name, [("/cloud/errors", T.String(data=text))])
    add("cloud is_bigendian wrong", [("/cloud", set_(pts(next(s)), is_bigendian=True))])
    add("cloud without its camera_info", [("/cloud", pts(next(s)))])
    add("cloud/camera_info NaN", [("/cloud/camera_info", set_(M.info(next(s)), k=np.full(9, math.nan)))])
    add("cloud/camera_info alone, 0x0", [("/cloud/camera_info", set_(M.info(next(s)), width=0, height=0))])
    add("plan/cloud empty", [("/plan/cloud", set_(pts(next(s)), width=0, row_step=0, data=u8(np.zeros(0, np.uint8))))])
    add("plan/cloud declares 2^32-1 points", [("/plan/cloud", set_(pts(next(s)), width=2**32 - 1))])
    p_ok = json.loads(json.dumps(ch["plan"]))
    S3 = next(s)
    p_ok["stamp_ns"] = S3
    add("valid plan, then its plan/cloud malformed", [("/plan", T.String(data=json.dumps(p_ok))),
                                                      ("/plan/cloud", set_(pts(S3), is_bigendian=True))])
    return cases


# ---- the live run -------------------------------------------------------------------------------

def play_demo_frame(player, build, stamp, timeout):
    play_frame(player, build(stamp))
    return wait_for(lambda: stamp in player.certified_stamps(), timeout, 0.1)


def run_flood(launch_file: str, input_mode: str, root: Path, monkeypatch) -> dict:
    from pws_ros.bridge import msgbuild, msgconv

    domain = 150 + os.getpid() % 50
    env = ros_env(root, domain)
    for k in ("ROS_DOMAIN_ID", "CYCLONEDDS_URI", "RMW_IMPLEMENTATION", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setenv(k, env[k])   # the test's own rclpy context: the same domain, loopback only
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)
    config = write_config(root / "flood.yaml", input_mode)
    launch = Launch(launch_file, {"config_file": str(config), "log_level": "info"}, root, env)
    proc, log_path = launch.proc, launch.log_path
    expected = LAUNCHES[launch_file]
    graph = None
    report: dict = {"launch": launch_file, "input_mode": input_mode, "max_memory_mb": MAX_MEMORY_MB}
    try:
        assert wait_for(lambda: set(launch.nodes()) >= set(expected) or proc.poll() is not None, 60), \
            f"the nodes did not start: {log_path.read_text()[-3000:]}"
        pids = launch.nodes()
        assert proc.poll() is None, log_path.read_text()[-3000:]
        graph = Player(domain, {**INPUTS, **INTERNAL, TF_STATIC: "TFMessage"}, "flood_player")
        T = graph.T
        M = Msgs(T)
        assert wait_for(lambda: graph.healthy_nodes() >= set(expected), 120), \
            f"no health from {set(expected) - graph.healthy_nodes()}: {log_path.read_text()[-3000:]}"
        entry = "pipeline" if launch_file == "pws.launch.py" else "cloud_listener"
        inputs = (POINTS, INFO) if input_mode == "pointcloud2" else (DEPTH, COLOR, INFO, POINTS)
        assert wait_for(lambda: graph.subscribed(inputs), 30), \
            f"{entry} did not subscribe to the inputs"
        if launch_file == "pws_nodes.launch.py":
            assert wait_for(lambda: graph.subscribed(INTERNAL), 30), \
                {t: graph.pubs[t].get_subscription_count() for t in INTERNAL}
        demo = demo_frames(T, points=input_mode == "pointcloud2")
        t_base = time.time_ns() // 10**9 * 10**9
        # warm-up: one valid demo frame (model loaded, first certification), then the baseline
        warm = t_base + 10**9
        assert play_demo_frame(graph, demo[0][0], warm, 180), f"no certification of the warm-up frame: {log_path.read_text()[-3000:]}"
        time.sleep(1.0)
        baseline = {name: status_kb(pid, "VmHWM") for name, pid in pids.items()}
        # the flood
        cases = flood_cases(M, t_base + 20 * 10**9)
        sent = Counter()
        t_flood = time.monotonic()
        n_before = len(graph.certs)
        for name, msgs in cases:
            for topic, msg in msgs:
                graph.publish(topic, msg)
                sent[topic] += 1
            # an input frame's case: give the node the time to answer it (an ERROR at once, a certificate
            # within a few seconds) before the next one replaces it (the online policy keeps the newest only)
            entered = {msgconv.header_stamp_ns(m) for t, m in msgs if t in ((POINTS,) if input_mode == "pointcloud2" else (DEPTH, COLOR))}
            if entered:
                wait_for(lambda: bool(entered & set(graph.certified_stamps())), 1.5, 0.02)
            else:
                time.sleep(0.02)
        # let it settle: no certification for 4 s (at most 90 s)
        last = [len(graph.certs), time.monotonic()]

        def settled():
            if len(graph.certs) != last[0]:
                last[:] = [len(graph.certs), time.monotonic()]
            return time.monotonic() - last[1] > 4.0
        wait_for(settled, 90, 0.2)
        report["flood_s"] = round(time.monotonic() - t_flood, 1)
        report["certifications_during_flood"] = len(graph.certs) - n_before
        # the valid demo afterwards, one frame at a time (each waits for its certification)
        got = []
        demo_base = t_base + 40_000 * 10**9
        for k, (build, label) in enumerate(demo[1:]):
            stamp = demo_base + k * 100_000_000
            if play_demo_frame(graph, build, stamp, 120):
                got.append((stamp, label))
            if len(got) >= DEMO_CERTIFICATIONS:
                break
        time.sleep(1.5)
        alive = {name: Path(f"/proc/{pid}").exists() for name, pid in pids.items()}
        peak = {name: status_kb(pid, "VmHWM") for name, pid in pids.items() if alive[name]}
        certs = {}
        for m in graph.messages():
            certs.setdefault(msgconv.stamp_to_ns(m.header.stamp), m)
        demo_results = []
        for stamp, label in got:
            msg = certs[stamp]
            parsed = msgbuild.parse_certification(msg)
            demo_results.append({"stamp": stamp, "label": label, "axes": {a: {"level": v["level"], "status": v["status"], "label": v["label"],
                                                                                "radius": v["radius"], "message": v["message"]}
                                                                            for a, v in parsed.items()},
                                 "keys_ok": all(tuple(st["keys"][:14]) == msgbuild.DIAGNOSTIC_KEYS
                                                for st in msgbuild.diagnostic_array_to_dicts(msg))})
        report.update({"cases": len(cases), "case_names": [c[0] for c in cases], "messages_sent": dict(sent),
                       "messages_total": sum(sent.values()), "alive": alive, "baseline_kb": baseline, "peak_kb": peak,
                       "demo": demo_results, "certifications_total": len(graph.certs)})
    finally:
        if graph is not None:
            graph.close()
        report["returncode"] = launch.stop()   # SIGINT to the group, as a terminal's Ctrl-C
    text = log_path.read_text(errors="replace")
    report["log_lines"] = text.count("\n")
    report["warn_error_lines"] = [ln for ln in text.splitlines() if re.search(r"\[(WARN|ERROR|FATAL)\]", ln)]
    report["log_tail"] = text[-4000:]
    out_dir = os.environ.get("PWS_FLOOD_REPORT")
    if out_dir:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        (Path(out_dir) / f"{launch_file}-{input_mode}.json").write_text(json.dumps(report, indent=1, default=str))
        (Path(out_dir) / f"{launch_file}-{input_mode}.log").write_text(text)
    report["log"] = text
    return report


# auto (the shipped default) locks onto RGB-D with the warm-up frame: the PointCloud2 cases are then
# ignored (counted); a third run takes the cloud as its input (the RGB-D cases are then the ignored ones)
RUNS = [("pws.launch.py", "auto"), ("pws_nodes.launch.py", "auto"), ("pws_nodes.launch.py", "pointcloud2")]


@pytest.mark.parametrize("launch_file,input_mode", RUNS)
def test_flooded_graph_survives_and_certifies_the_demo(launch_file, input_mode, tmp_path, monkeypatch):
    need_ros()
    r = run_flood(launch_file, input_mode, tmp_path, monkeypatch)
    text = r["log"]
    assert r["cases"] >= 90 and r["messages_total"] >= r["cases"], (r["cases"], r["messages_total"])
    assert all(r["alive"].values()), f"a node died: {r['alive']}\n{r['log_tail']}"
    assert "Traceback" not in text, text[text.index("Traceback") - 2000: text.index("Traceback") + 3000]
    assert "process has died" not in text, r["log_tail"]
    for name, kb in r["peak_kb"].items():
        grown_mb = (kb - r["baseline_kb"][name]) / 1024
        assert grown_mb < MAX_MEMORY_MB, f"{name}: peak RSS grew by {grown_mb:.0f} MiB (limit {MAX_MEMORY_MB} MiB)"
    assert len(r["demo"]) >= DEMO_CERTIFICATIONS, f"{len(r['demo'])} demo frames certified\n{r['log_tail']}"
    for d in r["demo"]:
        assert d["keys_ok"] and list(d["axes"]) == ["tz", "ry"]
        for axis, v in d["axes"].items():
            assert v["level"] in (0, 1), (axis, v)                 # certified, not certified or abstained; never ERROR
            assert v["label"] in (d["label"], -1), (axis, v, d["label"])
    # the bad inputs were answered by WARNs naming the problem; in the four-process mode every internal
    # topic's malformed messages too ("<topic>: ignoring a message: <problem>", throttled per topic)
    entry = "pipeline" if launch_file == "pws.launch.py" else "cloud_listener"
    input_warns = [ln for ln in r["warn_error_lines"] if f"[{entry}]: input: " in ln]
    # (each input case class has its own problem; the PointCloud2 run answers the 12 cloud cases, the others ~40 image cases)
    assert len(input_warns) >= (8 if input_mode == "pointcloud2" else 25), r["warn_error_lines"]
    if launch_file == "pws_nodes.launch.py":
        for topic in ("plan", "rendered/frames", "rendered/bounds", "rendered/errors", "cloud/errors"):
            assert any(f"]: {topic}: ignoring a message: " in ln for ln in r["warn_error_lines"]), topic
    assert r["returncode"] == 0, r["log_tail"]
