"""The four-process wire scheme (pws_ros.bridge.scheme): plans, frames and bounds cross CDR exactly,
the certifier's assembler ties every frame to its plan and detects a lost one."""
from __future__ import annotations

import numpy as np
import pytest

from pws_ros.bridge import msgbuild, scheme
from pws_ros.bridge.assembly import PartitionAssembler
from pws_ros.core.bounds import render_plan
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import cloud_from_rgbd
from pws_ros.core.errors import PwsError
from pws_ros.core.partition import plan_partitions

T = msgbuild.rosbags_types()
TS = T.typestore
STAMP = 1_700_000_000_250_000_000


def cdr(msg):
    return TS.deserialize_cdr(TS.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__)


@pytest.fixture(scope="module")
def rendered():
    intr = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5, "cam")
    depth = np.full((24, 32), 2.0)
    depth[6:18, 8:20] = 1.2
    rgb = np.random.default_rng(0).integers(0, 256, (24, 32, 3), dtype=np.uint8)
    cloud = cloud_from_rgbd(depth, rgb, intr)
    plan = plan_partitions(cloud, intr, "tx", 0.05, "pws_of")
    return intr, plan, render_plan(cloud, intr, plan)


def test_frame_tags():
    assert scheme.frame_tag(12, "tz", 3, 7) == "12/tz/3/7"
    tag = scheme.parse_frame_tag("12/Tz/3/7")
    assert (tag.stamp_ns, tag.axis, tag.index, tag.count) == (12, "tz", 3, 7)
    for bad, msg in (("12/tz/3", "is not"), ("x/tz/3/7", "non-integer"), ("12/yaw/3/7", "unknown motion axis"), ("12/tz/0/0", "count must be >= 1"),
                     ("12/tz/7/7", r"index 7 is outside \[0, 7\)"), ("12/tz/-1/7", "index -1"), ("9" * 30 + "/tz/0/2", "range of a ROS time")):
        with pytest.raises(PwsError, match=msg):
            scheme.parse_frame_tag(bad)
    with pytest.raises(PwsError, match="more than max_partitions 257"):  # the receiver's limit, before anything is built
        scheme.parse_frame_tag("12/tz/999999999/1000000000", max_count=257)
    assert scheme.parse_frame_tag("-5000000000/tz/0/3").stamp_ns == -5_000_000_000  # a negative stamp is a ROS time


def test_plan_bundle_roundtrip(rendered):
    intr, plan, _ = rendered
    bundle = scheme.PlanBundle(STAMP, "cam", "pws_of", intr.scaled(16, 12), ["tx", "rz"], {"tx": plan}, {"rz": "the plan needs 99999 partitions"})
    back = scheme.parse_plan_bundle_message(cdr(scheme.plan_bundle_message(bundle, T)))
    assert back.stamp_ns == STAMP and back.frame_id == "cam" and back.axes == ["tx", "rz"]
    assert back.camera == intr.scaled(16, 12)
    np.testing.assert_array_equal(back.plans["tx"].alphas, plan.alphas)  # exact through JSON
    assert back.plans["tx"].delta_alpha == plan.delta_alpha and back.errors == {"rz": "the plan needs 99999 partitions"}
    assert back.expected() == {"tx": len(plan.alphas), "rz": "the plan needs 99999 partitions"}


def test_plan_bundle_refusals():
    with pytest.raises(PwsError, match="not JSON"):
        scheme.plan_bundle_from_json("{")
    with pytest.raises(PwsError, match="is not a pws_ros/plan-bundle/1 bundle"):
        scheme.plan_bundle_from_json('{"format": "x"}')
    with pytest.raises(PwsError, match="lacks field 'camera'"):
        scheme.plan_bundle_from_json('{"format": "pws_ros/plan-bundle/1", "stamp_ns": 1, "frame_id": "", "method": "pws_of", "axes": ["tz"]}')


def test_frames_and_bounds_cross_exactly(rendered):
    intr, plan, rp = rendered
    n = len(plan.alphas)
    assert n >= 3 and len(rp.values.seg) > 0
    asm = PartitionAssembler()
    bundle = scheme.PlanBundle(STAMP, "cam", "pws_of", intr, ["tx"], {"tx": plan}, {})
    asm.expect(STAMP, bundle.expected(), info=bundle)
    for i in range(n):
        msg = cdr(scheme.frame_message(STAMP, "tx", i, n, rp.frames[i], T))
        assert msg.encoding == "32FC3" and msg.header.frame_id == f"{STAMP}/tx/{i}/{n}"
        tag, frame = scheme.parse_frame_message(msg)
        asm.add_frame(tag.stamp_ns, tag.axis, tag.index, tag.count, frame)
    b = scheme.parse_bounds_message(cdr(scheme.bounds_message(STAMP, "tx", rp, T)))
    assert (b.stamp_ns, b.axis, b.count, b.shape) == (STAMP, "tx", n, (24, 32))
    asm.add_bounds(b.stamp_ns, b.axis, b.count, b)
    (fr,) = asm.pop_ready()
    assert fr.complete and fr.info is bundle
    ax = fr.axes[0]
    back = scheme.rendered_plan_from_parts(bundle.plans["tx"], ax.frames, ax.bounds)
    np.testing.assert_array_equal(back.frames.numpy(), rp.frames.numpy())
    np.testing.assert_array_equal(back.pair_bound_sq, rp.pair_bound_sq)
    np.testing.assert_array_equal(back.values.seg, rp.values.seg)
    np.testing.assert_array_equal(back.values.pix, rp.values.pix)
    np.testing.assert_array_equal(back.values.val, rp.values.val)
    # the rebuilt sparse values reproduce the bounds from the frames
    np.testing.assert_allclose(back.values.pair_bound_sq(back.frames.numpy()), rp.pair_bound_sq, rtol=1e-12)


def test_lost_frame_on_the_wire_is_never_certified(rendered):
    intr, plan, rp = rendered
    n = len(plan.alphas)
    asm = PartitionAssembler()
    asm.expect(STAMP, {"tx": n})
    for i in range(n):
        if i == 1:
            continue  # lost in transport
        tag, frame = scheme.parse_frame_message(scheme.frame_message(STAMP, "tx", i, n, rp.frames[i], T))
        asm.add_frame(tag.stamp_ns, tag.axis, tag.index, tag.count, frame)
    (fr,) = asm.pop_ready()
    assert not fr.complete and fr.axes[0].frames is None and "lost frame(s) 1" in fr.axes[0].error


def test_malformed_frames_and_bounds(rendered):
    _, plan, rp = rendered
    msg = scheme.frame_message(STAMP, "tx", 0, 3, rp.frames[0], T)
    msg.header.stamp = msgbuild.make_time(T, STAMP + 1)
    with pytest.raises(PwsError, match="different from its tag"):
        scheme.parse_frame_message(msg)
    msg = msgbuild.image_from_numpy(msgbuild.make_header(T, 5, "5/tx/0/3"), np.zeros((2, 2, 3), np.uint8), T)
    with pytest.raises(PwsError, match="expected 32FC3"):
        scheme.parse_frame_message(msg)
    b = scheme.bounds_message(STAMP, "tx", rp, T)
    b.data = b.data[:-1]
    with pytest.raises(PwsError, match="holds .* numbers, expected"):
        scheme.parse_bounds_message(b)
    b = scheme.bounds_message(STAMP, "tx", rp, T)
    b.layout.dim[0].label = "other/1/tx/3"
    with pytest.raises(PwsError, match="is not 'pws_bounds/"):
        scheme.parse_bounds_message(b)
    with pytest.raises(PwsError, match="must be \\(H, W, 3\\)"):
        scheme.frame_message(STAMP, "tx", 0, 3, np.zeros((4, 4)), T)


def test_preview_image():
    f = np.array([[[0.0, 0.5, 1.0], [-0.2, 1.3, 0.25]]], dtype=np.float32)
    np.testing.assert_array_equal(scheme.preview_image(f), [[[0, 128, 255], [0, 255, 64]]])
