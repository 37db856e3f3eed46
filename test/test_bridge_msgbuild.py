"""Core -> message builders (pws_ros.bridge.msgbuild) with rosbags classes: the certification key
schema, levels, poses, markers, health; every message survives CDR serialisation."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pws_ros.bridge import msgbuild, msgconv
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.errors import PwsError
from pws_ros.core.motion import AXES, camera_pose, project
from pws_ros.core.result import STATUS_ABSTAIN, STATUS_CERTIFIED, STATUS_NOT_CERTIFIED, Certificate, error_certificate

T = msgbuild.rosbags_types()
TS = T.typestore


def cdr_roundtrip(msg):
    name = msg.__msgtype__
    return TS.deserialize_cdr(TS.serialize_cdr(msg, name), name)


def cert(axis="tz", status=STATUS_CERTIFIED, **kw):
    base = dict(axis=axis, unit="m" if axis[0] == "t" else "rad", method="pws_of", coverage="pairwise", requested_radius=0.01,
                status=status, certified=status == STATUS_CERTIFIED, radius=0.01 if status == STATUS_CERTIFIED else 0.004,
                label=3, class_name="mug", p_a_lower=[0.93, 0.91, 0.95], sigma=0.5, n0=64, n=256, alpha=0.01, num_bounds=3,
                num_partitions=3, delta_alpha=0.01, frames_rendered=3, classifier_calls=64 + 3 * 256,
                timings={"total": 0.25}, reason="" if status == STATUS_CERTIFIED else "segment 2 not covered")
    base.update(kw)
    return Certificate(**base)


def test_diagnostic_array_key_schema_and_levels():
    hdr = msgbuild.make_header(T, 1_700_000_000_123_456_789, "camera_color_optical_frame")
    certs = [cert("tz"), cert("ry", STATUS_NOT_CERTIFIED), cert("rx", STATUS_ABSTAIN, label=-1, class_name=""),
             error_certificate("tx", "m", "pws_of", "pairwise", 0.005, "the plan needs 30001 partitions")]
    msg = msgbuild.certificates_to_diagnostic_array(hdr, certs, node_name="pipeline", types=T, latency_ms=812.5, compute_ms=None)
    msg = cdr_roundtrip(msg)
    assert msg.header.stamp.sec == 1_700_000_000 and msg.header.stamp.nanosec == 123_456_789
    assert msg.header.frame_id == "camera_color_optical_frame"
    parsed = msgbuild.diagnostic_array_to_dicts(msg)
    assert [p["name"] for p in parsed] == ["pws/tz", "pws/ry", "pws/rx", "pws/tx"]
    assert [p["level"] for p in parsed] == [0, 1, 1, 2]  # OK, WARN, WARN, ERROR
    for p in parsed:
        assert p["hardware_id"] == "camera_color_optical_frame"
        assert tuple(p["keys"][:14]) == msgbuild.DIAGNOSTIC_KEYS
        assert tuple(p["keys"][14:]) == msgbuild.DIAGNOSTIC_EXTRA_KEYS
        assert p["values"]["latency_ms"] == "812.5"
    tz = parsed[0]["values"]
    assert tz["label"] == "3" and tz["class_name"] == "mug" and tz["certified"] == "true"
    assert float(tz["radius"]) == 0.01 and tz["unit"] == "m" and float(tz["p_a_lower"]) == 0.91
    assert tz["sigma"] == "0.5" and tz["n"] == "256" and tz["alpha"] == "0.01" and tz["num_partitions"] == "3"
    assert tz["classifier_calls"] == str(64 + 768) and float(tz["compute_ms"]) == 250.0 and tz["node"] == "pipeline"
    assert parsed[1]["values"]["certified"] == "false"
    assert "not certified" in parsed[1]["message"] and "segment 2" in parsed[1]["message"]
    assert parsed[2]["message"].startswith("abstained")
    assert parsed[3]["message"] == "could not certify: the plan needs 30001 partitions"
    assert parsed[3]["values"]["p_a_lower"] == "nan"
    typed = msgbuild.parse_certification(msg)
    assert typed["tz"]["certified"] is True and typed["tz"]["radius"] == 0.01 and typed["tx"]["level"] == 2


def test_compute_ms_per_axis_and_scalar():
    hdr = msgbuild.make_header(T, 5, "f")
    certs = [cert("tz"), cert("ry")]
    for compute, expect in ((12.0, ["12", "12"]), ({"tz": 1.5, "ry": 2.5}, ["1.5", "2.5"]), ([3.0, 4.0], ["3", "4"])):
        msg = msgbuild.certificates_to_diagnostic_array(hdr, certs, node_name="n", types=T, latency_ms=0.0, compute_ms=compute)
        assert [d["values"]["compute_ms"] for d in msgbuild.diagnostic_array_to_dicts(msg)] == expect


def test_parse_certification_rejects_foreign_schema():
    hdr = msgbuild.make_header(T, 5, "f")
    msg = msgbuild.certificates_to_diagnostic_array(hdr, [cert()], node_name="n", types=T, latency_ms=0.0)
    msg.status[0].values = list(reversed(msg.status[0].values))
    with pytest.raises(PwsError, match="do not follow the schema"):
        msgbuild.parse_certification(msg)


def test_reason_with_newlines_stays_one_line():
    c = error_certificate("tz", "m", "pws_of", "pairwise", 0.01, "first line\nsecond line")
    msg = msgbuild.certificates_to_diagnostic_array(msgbuild.make_header(T, 0), [c], node_name="n", types=T, latency_ms=1.0)
    assert msgbuild.diagnostic_array_to_dicts(msg)[0]["values"]["reason"] == "first line second line"


def quat_to_matrix(x, y, z, w):
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1))
def test_quaternion_from_matrix_property(v):
    q = np.asarray(v) / np.linalg.norm(v)
    R = quat_to_matrix(*q)
    got = msgbuild.quaternion_from_matrix(R)
    np.testing.assert_allclose(quat_to_matrix(*got), R, atol=1e-9)
    assert got[3] >= 0


class _Plan:
    def __init__(self, axis, alphas):
        self.axis, self.alphas = axis, np.asarray(alphas)


@pytest.mark.parametrize("axis", AXES)
def test_plan_to_pose_array_matches_camera_pose(axis):
    alphas = np.linspace(-0.3, 0.3, 7)
    msg = cdr_roundtrip(msgbuild.plan_to_pose_array(msgbuild.make_header(T, 42, "opt"), _Plan(axis, alphas), T))
    assert msg.header.frame_id == "opt" and len(msg.poses) == 7
    intr = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)
    P = np.array([[0.2, -0.1, 1.5], [-0.3, 0.2, 2.0]])
    for a, pose in zip(alphas, msg.poses):
        R, t = camera_pose(axis, a)
        o = pose.orientation
        np.testing.assert_allclose(quat_to_matrix(o.x, o.y, o.z, o.w), R, atol=1e-12)
        np.testing.assert_allclose([pose.position.x, pose.position.y, pose.position.z], t, atol=1e-15)
        # the pose is what the renderer uses: P' = R^T (P - t) projects like core.motion.project
        Pp = (P - t) @ R
        u = intr.fx * Pp[:, 0] / Pp[:, 2] + intr.cx + 0.5
        u_ref, _, _ = project(P, intr, axis, a)
        np.testing.assert_allclose(u, u_ref, atol=1e-9)


def test_markers_health_camera_info_serialise():
    hdr = msgbuild.make_header(T, 7, "opt")
    certs = [cert("tz"), cert("ry", STATUS_NOT_CERTIFIED), error_certificate("rx", "rad", "pws_of", "pairwise", 0.01, "boom")]
    ma = cdr_roundtrip(msgbuild.markers_for(hdr, certs, T))
    assert [m.type for m in ma.markers] == [T.Marker.TEXT_VIEW_FACING] * 3
    assert len({m.id for m in ma.markers}) == 3
    assert "tz" in ma.markers[0].text and "OK" in ma.markers[0].text and "error" in ma.markers[2].text
    assert ma.markers[0].color.g > 0.5 and ma.markers[2].color.r > 0.5
    health = cdr_roundtrip(msgbuild.health_status(hdr, node_name="pipeline", types=T, rate_hz=0.5, frames_in=10, frames_processed=3,
                                                  frames_dropped=7, device="cpu", extra={"warning_fallback": "cuda:0 -> cpu"}))
    d = msgbuild.diagnostic_array_to_dicts(health)[0]
    assert d["name"] == "pipeline: health" and d["level"] == 0 and d["message"] == "3 frames processed, 7 dropped"
    planner = msgbuild.health_status(hdr, node_name="partition_planner", types=T, rate_hz=0.5, frames_in=10, frames_processed=3,
                                     frames_dropped=7, device="cpu", activity="planned")
    assert msgbuild.diagnostic_array_to_dicts(planner)[0]["message"] == "3 frames planned, 7 dropped"
    assert d["values"]["frames_dropped"] == "7" and d["values"]["device"] == "cpu" and d["keys"][-1] == "warning_fallback"
    err = msgbuild.health_status(hdr, node_name="p", types=T, rate_hz=0, frames_in=0, frames_processed=0, frames_dropped=0,
                                 device="cpu", last_error="model not found")
    assert msgbuild.diagnostic_array_to_dicts(err)[0]["level"] == 2
    warn = msgbuild.health_status(hdr, node_name="p", types=T, rate_hz=0, frames_in=0, frames_processed=0, frames_dropped=0,
                                  device="cpu", warning="fell back to cpu")
    assert msgbuild.diagnostic_array_to_dicts(warn)[0]["level"] == 1
    intr = CameraIntrinsics(32, 24, 30.0, 31.0, 15.5, 11.5, "opt")
    info = cdr_roundtrip(msgbuild.camera_info_from_intrinsics(hdr, intr, T))
    back = msgconv.intrinsics_from_camera_info(info)
    assert (back.width, back.height, back.fx, back.fy, back.cx, back.cy, back.frame_id) == (32, 24, 30.0, 31.0, 15.5, 11.5, "opt")


def test_image_from_numpy_refusals_and_torch():
    import torch

    hdr = msgbuild.make_header(T, 1)
    with pytest.raises(PwsError, match="rgb8 needs a uint8 array"):
        msgbuild.image_from_numpy(hdr, np.zeros((2, 2, 3), np.float32), T, encoding="rgb8")
    with pytest.raises(PwsError, match="no image encoding"):
        msgbuild.image_from_numpy(hdr, np.zeros((2, 2, 2), np.uint8), T)
    t = torch.rand(3, 4, 3)
    msg = cdr_roundtrip(msgbuild.image_from_numpy(hdr, t, T))
    np.testing.assert_array_equal(msgconv.image_to_numpy(msg), t.numpy())


def test_stamps():
    assert msgconv.stamp_to_ns(msgbuild.make_time(T, 3_000_000_007)) == 3_000_000_007
    # negative stamps are valid ROS times (int32 sec, nanosec in [0, 1e9)): a frame stamped -5 s is certified
    for ns in (-1, -5_000_000_000, -5_000_000_001):
        t = msgbuild.make_time(T, ns)
        assert 0 <= t.nanosec < 1_000_000_000 and msgconv.stamp_to_ns(t) == ns
    with pytest.raises(PwsError, match="outside the range of a ROS time"):
        msgbuild.make_time(T, 2**31 * 1_000_000_000)
    h = msgbuild.copy_header(T, msgbuild.make_header(T, 99, "a"), frame_id="b")
    assert msgconv.stamp_to_ns(h.stamp) == 99 and h.frame_id == "b"


def test_pack_rgb_matches_pcl_layout():
    packed = msgbuild.pack_rgb(np.array([[1.0, 0.5, 0.0]])).view(np.uint32)[0]
    assert packed == (255 << 16) | (128 << 8) | 0
    assert not math.isnan(msgbuild.pack_rgb(np.array([[1.0, 1.0, 1.0]]))[0])
