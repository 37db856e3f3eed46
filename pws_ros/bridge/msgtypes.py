"""The message-class namespace ``types`` (rclpy or rosbags) and the basic pieces every builder uses
(:func:`make`, headers, times, poses).

Builders take ``types``: a namespace whose attributes are message classes (``types.Image``,
``types.Header`` ...) plus three converters for array fields (``types.u8`` for ``uint8[]``,
``types.f64`` for ``float64[]``, ``types.f64fixed`` for ``float64[N]``), because rclpy and
rosbags want different Python types there. :func:`rosbags_types` builds it from a rosbags
typestore (tests, bag writing); :func:`pws_ros.nodes._ros.rclpy_types` from the installed ROS 2
message packages. Every field is passed as a keyword (rosbags constructors have no defaults;
fields a class does not know, e.g. newer ``Marker`` fields on an older distro, are left out).
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np

from ..core.errors import require

# message classes a ``types`` namespace provides (ROS 2 package/msg/Name)
MESSAGE_TYPES: dict[str, str] = {
    "Time": "builtin_interfaces/msg/Time",
    "Duration": "builtin_interfaces/msg/Duration",
    "Header": "std_msgs/msg/Header",
    "String": "std_msgs/msg/String",
    "ColorRGBA": "std_msgs/msg/ColorRGBA",
    "Float64MultiArray": "std_msgs/msg/Float64MultiArray",
    "MultiArrayLayout": "std_msgs/msg/MultiArrayLayout",
    "MultiArrayDimension": "std_msgs/msg/MultiArrayDimension",
    "Image": "sensor_msgs/msg/Image",
    "CompressedImage": "sensor_msgs/msg/CompressedImage",
    "CameraInfo": "sensor_msgs/msg/CameraInfo",
    "RegionOfInterest": "sensor_msgs/msg/RegionOfInterest",
    "PointCloud2": "sensor_msgs/msg/PointCloud2",
    "PointField": "sensor_msgs/msg/PointField",
    "Point": "geometry_msgs/msg/Point",
    "Quaternion": "geometry_msgs/msg/Quaternion",
    "Vector3": "geometry_msgs/msg/Vector3",
    "Pose": "geometry_msgs/msg/Pose",
    "PoseArray": "geometry_msgs/msg/PoseArray",
    "DiagnosticArray": "diagnostic_msgs/msg/DiagnosticArray",
    "DiagnosticStatus": "diagnostic_msgs/msg/DiagnosticStatus",
    "KeyValue": "diagnostic_msgs/msg/KeyValue",
    "Marker": "visualization_msgs/msg/Marker",
    "MarkerArray": "visualization_msgs/msg/MarkerArray",
    "MeshFile": "visualization_msgs/msg/MeshFile",
}


def rosbags_types(store: Any = None) -> SimpleNamespace:
    """The ``types`` namespace from a rosbags typestore (default ROS 2 Jazzy)."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(store if store is not None else Stores.ROS2_JAZZY)
    ns = SimpleNamespace(typestore=ts, flavour="rosbags")
    for attr, name in MESSAGE_TYPES.items():
        if name in ts.types:
            setattr(ns, attr, ts.types[name])
    ns.u8 = lambda a: np.ascontiguousarray(np.asarray(a, dtype=np.uint8).reshape(-1))
    ns.f64 = lambda a: np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(-1))
    ns.f64fixed = ns.f64
    return ns


def _fields_of(cls: Any) -> set[str] | None:
    getter = getattr(cls, "get_fields_and_field_types", None)  # rclpy
    if getter is not None:
        try:
            return set(getter().keys())
        except Exception:  # pragma: no cover - defensive
            return None
    if dataclasses.is_dataclass(cls):  # rosbags
        return {f.name for f in dataclasses.fields(cls)}
    return None


def make(cls: Any, **fields: Any) -> Any:
    """``cls(**fields)`` keeping only the fields ``cls`` declares (distros differ, e.g. Marker)."""
    known = _fields_of(cls)
    if known is not None:
        fields = {k: v for k, v in fields.items() if k in known}
    return cls(**fields)


# ---- basic pieces -------------------------------------------------------------------------

def make_time(types: Any, stamp_ns: int) -> Any:
    """A ``builtin_interfaces/Time`` (int32 ``sec``, uint32 ``nanosec`` in [0, 1e9)) of ``stamp_ns``.
    Negative stamps are valid ROS times (a simulation clock, a driver that sends them: ``sec`` < 0), and a
    frame stamped so is certified like any other in both modes."""
    stamp_ns = int(stamp_ns)
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    require(-(2**31) <= sec < 2**31, f"stamp {stamp_ns} ns is outside the range of a ROS time (int32 seconds)")
    return make(types.Time, sec=sec, nanosec=nanosec)


def make_header(types: Any, stamp_ns: int, frame_id: str = "") -> Any:
    return make(types.Header, stamp=make_time(types, stamp_ns), frame_id=str(frame_id))


def copy_header(types: Any, header: Any, frame_id: str | None = None) -> Any:
    """A header of ``types`` with the stamp of ``header`` (any flavour) and its or a new frame id."""
    return make(types.Header, stamp=make(types.Time, sec=int(header.stamp.sec), nanosec=int(header.stamp.nanosec)),
                frame_id=str(header.frame_id if frame_id is None else frame_id))


def quaternion_from_matrix(R: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (Shepperd's method, w >= 0)."""
    R = np.asarray(R, dtype=np.float64)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        w, x, y, z = 0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        w, x, y, z = (R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        w, x, y, z = (R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        w, x, y, z = (R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s
    q = np.array([x, y, z, w])
    q /= np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def make_pose(types: Any, R: np.ndarray, t: np.ndarray) -> Any:
    x, y, z, w = quaternion_from_matrix(R)
    return make(types.Pose,
                position=make(types.Point, x=float(t[0]), y=float(t[1]), z=float(t[2])),
                orientation=make(types.Quaternion, x=x, y=y, z=z, w=w))


def identity_pose(types: Any, position: Sequence[float] = (0.0, 0.0, 0.0)) -> Any:
    return make_pose(types, np.eye(3), np.asarray(position, dtype=float))


__all__ = ["MESSAGE_TYPES", "copy_header", "identity_pose", "make", "make_header", "make_pose", "make_time", "quaternion_from_matrix",
           "rosbags_types"]
