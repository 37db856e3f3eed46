"""Core objects -> ROS 2 messages, for any message-class namespace (rclpy or rosbags): the sensor
messages (images, camera info, point clouds, pose arrays) here; the ``types`` namespace and basic
pieces in :mod:`pws_ros.bridge.msgtypes`; the certification DiagnosticArray (its key schema),
markers and health status in :mod:`pws_ros.bridge.diagnostics`. Every public name of those two is
importable from here too (``from pws_ros.bridge.msgbuild import parse_certification``).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..core.cloud import Cloud
from ..core.errors import PwsError, require
from ..core.motion import camera_pose
from .cloudconv import FILLED_FIELD
from .diagnostics import (CERTIFIED_LABEL_KEYS, CERTIFIED_LABEL_STATUS, DIAGNOSTIC_EXTRA_KEYS, DIAGNOSTIC_KEYS, LEVEL_FOR_STATUS,
                          STATUS_NAME_PREFIX, certificate_message, certificate_values, certificates_to_diagnostic_array,
                          certified_label, certified_label_array, diagnostic_array_to_dicts, health_status, level_to_int,
                          level_value, marker_text, markers_for, parse_certification)
from .msgtypes import (MESSAGE_TYPES, copy_header, identity_pose, make, make_header, make_pose, make_time, quaternion_from_matrix,
                       rosbags_types)


# ---- images, clouds, poses ----------------------------------------------------------------

def image_from_numpy(header: Any, array: np.ndarray, types: Any, encoding: str | None = None) -> Any:
    """A ``sensor_msgs/Image`` (little-endian, no row padding) from an array.

    uint8 ``(H, W, 3)`` -> ``rgb8`` (or ``bgr8`` if asked; the array is RGB), uint8 ``(H, W)`` ->
    ``mono8``, uint16 ``(H, W)`` -> ``16UC1``, float ``(H, W)`` -> ``32FC1``, float ``(H, W, 3)`` ->
    ``32FC3``. Torch tensors are accepted (moved to the CPU).
    """
    if hasattr(array, "detach"):
        array = array.detach().cpu().numpy()
    a = np.asarray(array)
    require(a.ndim in (2, 3) and a.shape[0] > 0 and a.shape[1] > 0, f"image array must be (H, W) or (H, W, C), got shape {a.shape}")
    H, W = a.shape[:2]
    C = 1 if a.ndim == 2 else a.shape[2]
    if encoding is None:
        if a.dtype == np.uint8:
            encoding = {1: "mono8", 3: "rgb8", 4: "rgba8"}.get(C, "")
        elif a.dtype == np.uint16 and C == 1:
            encoding = "16UC1"
        elif np.issubdtype(a.dtype, np.floating):
            encoding = {1: "32FC1", 3: "32FC3"}.get(C, "")
        require(bool(encoding), f"no image encoding for an array of {a.dtype} with {C} channel(s)")
    enc = encoding
    key = enc.lower()
    if key in ("rgb8", "bgr8", "rgba8", "bgra8", "mono8"):
        need = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}[key]
        require(a.dtype == np.uint8 and C == need, f"{enc} needs a uint8 array with {need} channel(s), got {a.dtype} with {C}")
        out = a.reshape(H, W, C)
        if key in ("bgr8", "bgra8"):
            out = np.concatenate([out[:, :, 2::-1], out[:, :, 3:]], axis=2)
        data = np.ascontiguousarray(out).reshape(-1)
        step = W * C
    elif key in ("16uc1", "mono16"):
        require(a.dtype == np.uint16 and C == 1, f"{enc} needs a uint16 (H, W) array, got {a.dtype} with {C} channel(s)")
        data = np.ascontiguousarray(a.astype("<u2")).view(np.uint8).reshape(-1)
        step = W * 2
    elif key in ("32fc1", "32fc3"):
        need = 1 if key == "32fc1" else 3
        require(C == need, f"{enc} needs {need} channel(s), got {C}")
        data = np.ascontiguousarray(a.astype("<f4")).view(np.uint8).reshape(-1)
        step = W * 4 * need
    else:
        raise PwsError(f"cannot build an Image with encoding {enc!r}")
    return make(types.Image, header=header, height=int(H), width=int(W), encoding=enc, is_bigendian=0,
                step=int(step), data=types.u8(data))


def camera_info_from_intrinsics(header: Any, intr: Any, types: Any) -> Any:
    """A ``sensor_msgs/CameraInfo`` (no distortion, identity R, P = [K | 0])."""
    K = np.array([intr.fx, 0.0, intr.cx, 0.0, intr.fy, intr.cy, 0.0, 0.0, 1.0])
    P = np.array([intr.fx, 0.0, intr.cx, 0.0, 0.0, intr.fy, intr.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    return make(types.CameraInfo, header=header, height=int(intr.height), width=int(intr.width),
                distortion_model="plumb_bob", d=types.f64(np.zeros(5)), k=types.f64fixed(K),
                r=types.f64fixed(np.eye(3).reshape(-1)), p=types.f64fixed(P), binning_x=0, binning_y=0,
                roi=make(types.RegionOfInterest, x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def pack_rgb(colors: np.ndarray) -> np.ndarray:
    """(N, 3) float colours in [0, 1] -> (N,) float32 with the bits of ``0x00RRGGBB`` (PCL ``rgb``)."""
    c = np.clip(np.rint(np.asarray(colors, dtype=np.float64) * 255.0), 0, 255).astype(np.uint32)
    packed = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    return packed.astype("<u4").view("<f4")


def cloud_to_pointcloud2(header: Any, cloud: Cloud, types: Any, organized_shape: tuple[int, int] | None = None) -> Any:
    """An xyz + packed-rgb ``PointCloud2`` (float32 x, y, z at 0, 4, 8; rgb at 12; point_step 16).

    Unorganized (height 1) unless ``organized_shape`` ``(H, W)`` with ``H * W == len(cloud)``. A cloud
    with filled points it knows (``cloud.filled_mask``) also gets the UINT8 field
    :data:`~pws_ros.bridge.cloudconv.FILLED_FIELD` at 16 (1: filled depth; point_step 20).
    """
    n = len(cloud)
    if organized_shape is not None:
        H, W = (int(v) for v in organized_shape)
        require(H * W == n, f"organized shape {W}x{H} does not hold {n} points")
    else:
        H, W = 1, n
    mask = cloud.filled_mask if cloud.filled > 0 else None
    layout = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4")]
    if mask is not None:
        layout += [(FILLED_FIELD, "u1"), ("_pad", "u1", (3,))]
    rec = np.zeros(n, dtype=layout)
    pts = np.asarray(cloud.points)
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["rgb"] = pack_rgb(cloud.colors)
    fields = [make(types.PointField, name=name, offset=off, datatype=7, count=1)
              for name, off in (("x", 0), ("y", 4), ("z", 8), ("rgb", 12))]
    if mask is not None:
        rec[FILLED_FIELD] = mask
        fields.append(make(types.PointField, name=FILLED_FIELD, offset=16, datatype=2, count=1))
    step = rec.dtype.itemsize
    return make(types.PointCloud2, header=header, height=H, width=W, fields=fields, is_bigendian=False,
                point_step=step, row_step=step * W, data=types.u8(rec.view(np.uint8).reshape(-1)),
                is_dense=bool(np.all(np.isfinite(pts))))


def plan_to_pose_array(header: Any, plan: Any, types: Any) -> Any:
    """The camera poses of a plan (``plan.axis``, ``plan.alphas``) in the source optical frame,
    in partition order: pose ``i`` is the moved camera ``(R, t) = camera_pose(axis, alphas[i])``."""
    alphas = np.asarray(plan.alphas, dtype=np.float64).reshape(-1)
    poses = []
    for a in alphas:
        R, t = camera_pose(plan.axis, float(a))
        poses.append(make_pose(types, R, t))
    return make(types.PoseArray, header=header, poses=poses)


__all__ = [
    "CERTIFIED_LABEL_KEYS", "CERTIFIED_LABEL_STATUS", "DIAGNOSTIC_EXTRA_KEYS", "DIAGNOSTIC_KEYS", "LEVEL_FOR_STATUS", "MESSAGE_TYPES",
    "STATUS_NAME_PREFIX", "camera_info_from_intrinsics", "certificate_message", "certificate_values",
    "certificates_to_diagnostic_array", "certified_label", "certified_label_array", "cloud_to_pointcloud2", "copy_header",
    "diagnostic_array_to_dicts", "health_status", "identity_pose", "image_from_numpy", "level_to_int", "level_value", "make",
    "make_header", "make_pose", "make_time", "marker_text", "markers_for", "pack_rgb", "parse_certification", "plan_to_pose_array",
    "quaternion_from_matrix", "rosbags_types",
]
