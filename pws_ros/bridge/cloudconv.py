"""``sensor_msgs/PointCloud2`` -> numpy arrays, a :class:`~pws_ros.core.cloud.Cloud` and the camera
to render it with (duck-typed: rclpy or rosbags messages; PwsError naming what is malformed).

A ``PointCloud2`` needs ``x, y, z`` (float32 or float64, any offsets); colour is optional: a packed
``rgb``/``rgba`` field (float32 or uint32/int32 holding ``0x00RRGGBB``) or separate ``r, g, b``
uint8 fields. Row padding and ``is_bigendian`` are honoured. Points with a non-finite coordinate, or
exactly at the origin (the "no return" marker of several drivers), are dropped.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.cloud import DEPTH_FILLS, Cloud, fill_depth, require_valid_share
from ..core.errors import PwsError, require
from .msgconv import as_byte_array, byte_rows, frame_id_of, intrinsics_from_camera_info

# sensor_msgs/PointField datatypes
POINTFIELD_DTYPES = {1: np.int8, 2: np.uint8, 3: np.int16, 4: np.uint16, 5: np.int32, 6: np.uint32, 7: np.float32, 8: np.float64}
# A UINT8 field of the clouds this package publishes (``cloud``, ``plan/cloud``): 1 where the point's depth
# was filled (depth_fill), not measured; it carries the certificate's filled_points across the four processes
FILLED_FIELD = "pws_filled"
POINTFIELD_NAMES = {1: "INT8", 2: "UINT8", 3: "INT16", 4: "UINT16", 5: "INT32", 6: "UINT32", 7: "FLOAT32", 8: "FLOAT64"}


@dataclass
class PointCloudArrays:
    """Every point of a PointCloud2 in message order: ``xyz`` (M, 3) float64 with NaN where invalid,
    ``rgb`` (M, 3) uint8 (or None without colour), ``valid`` (M,) bool, ``shape`` (H, W)."""

    xyz: np.ndarray
    rgb: np.ndarray | None
    valid: np.ndarray
    shape: tuple[int, int]
    frame_id: str = ""
    filled: np.ndarray | None = None   # (M,) bool: the FILLED_FIELD of a cloud this package wrote (filled depth)

    @property
    def organized(self) -> bool:
        return self.shape[0] > 1


class CloudConversion(tuple):
    """``(cloud, organized_shape)``: unpacks as a pair; also has ``has_color`` (False: grey 0.5 was
    used), ``valid`` (mask over the message's points), ``arrays`` (:class:`PointCloudArrays`)."""

    def __new__(cls, cloud: Cloud, organized_shape: tuple[int, int] | None, has_color: bool, arrays: PointCloudArrays):
        self = super().__new__(cls, (cloud, organized_shape))
        self.cloud = cloud
        self.organized_shape = organized_shape
        self.has_color = bool(has_color)
        self.arrays = arrays
        self.valid = arrays.valid
        return self


def _field_table(msg: Any) -> dict[str, tuple[int, int, int]]:
    table: dict[str, tuple[int, int, int]] = {}
    for f in list(getattr(msg, "fields", []) or []):
        name = str(f.name)
        dt, off, cnt = int(f.datatype), int(f.offset), int(getattr(f, "count", 1) or 1)
        require(dt in POINTFIELD_DTYPES, f"PointCloud2 field {name!r} has unknown datatype {dt}")
        require(off >= 0, f"PointCloud2 field {name!r} has a negative offset {off}")
        table.setdefault(name, (off, dt, cnt))
    return table


PLAUSIBLE_M = (1e-6, 1e6)   # |coordinate| of a point a camera measured, in metres (or exactly 0)


def _plausible_share(xyz: np.ndarray) -> float:
    """The share of the finite non-origin points whose x, y, z are each 0 or within ``PLAUSIBLE_M``
    (NaN/inf and origin points are a driver's "no return", not evidence)."""
    with np.errstate(invalid="ignore", over="ignore"):
        a = np.abs(xyz)
        ok = np.all((a == 0) | ((a >= PLAUSIBLE_M[0]) & (a <= PLAUSIBLE_M[1])), axis=1)
        used = np.any(xyz != 0, axis=1) & np.all(np.isfinite(xyz), axis=1)
    n = int(used.sum())
    return float((ok & used).sum()) / n if n else 1.0


def _check_byte_order(xyz: np.ndarray, fields: dict[str, tuple[int, int, int]], pts: np.ndarray, big: bool) -> None:
    """PwsError when ``is_bigendian`` is evidently wrong: the coordinates read in the declared byte order
    are mostly implausible (denormal ~1e-41 m, or beyond 1e6 m) and read in the other order they are
    plausible. Certifying such a cloud would certify garbage points (seen live: z ~ 4.6e-41 m)."""
    if len(xyz) == 0 or _plausible_share(xyz) >= 0.5:
        return
    swapped = []
    for axis in ("x", "y", "z"):
        off, dt, _ = fields[axis]
        dtype = np.dtype(POINTFIELD_DTYPES[dt]).newbyteorder("<" if big else ">")
        swapped.append(np.ascontiguousarray(pts[:, off: off + dtype.itemsize]).view(dtype).reshape(-1).astype(np.float64))
    if _plausible_share(np.stack(swapped, axis=1)) >= 0.9:
        declared, other = ("big", "little") if big else ("little", "big")
        raise PwsError(f"PointCloud2 says is_bigendian={bool(big)}, but its x, y, z read {declared}-endian are implausible "
                       f"(|coordinate| below {PLAUSIBLE_M[0]:g} m or above {PLAUSIBLE_M[1]:g} m) and read {other}-endian they are "
                       f"plausible: the publisher sets is_bigendian wrongly")


def pointcloud2_to_arrays(msg: Any) -> PointCloudArrays:
    """Decode a ``sensor_msgs/PointCloud2`` (any field offsets, padding, endianness, layout)."""
    width = int(getattr(msg, "width", 0))
    height = int(getattr(msg, "height", 0))
    require(width >= 0 and height >= 0, f"PointCloud2 has a negative size {width}x{height}")
    point_step = int(msg.point_step)
    row_step = int(msg.row_step)
    big = bool(msg.is_bigendian)
    fields = _field_table(msg)
    names = ", ".join(fields) or "none"
    for axis in ("x", "y", "z"):
        require(axis in fields, f"PointCloud2 has no {axis!r} field (fields: {names})")
        dt = fields[axis][1]
        require(dt in (7, 8), f"PointCloud2 field {axis!r} is {POINTFIELD_NAMES[dt]}: expected FLOAT32 or FLOAT64")
    color_field = next((n for n in ("rgb", "rgba") if n in fields), None)
    separate = color_field is None and all(c in fields for c in ("r", "g", "b"))
    used = ["x", "y", "z"] + ([color_field] if color_field else []) + (["r", "g", "b"] if separate else [])
    for name in used:
        off, dt, _ = fields[name]
        size = np.dtype(POINTFIELD_DTYPES[dt]).itemsize
        require(off + size <= point_step, f"PointCloud2 field {name!r} (offset {off}, {size} bytes) does not fit in point_step {point_step}")
    if color_field:
        dt = fields[color_field][1]
        require(dt in (5, 6, 7), f"PointCloud2 field {color_field!r} is {POINTFIELD_NAMES[dt]}: expected packed FLOAT32 or UINT32")
    if separate:
        for c in ("r", "g", "b"):
            require(fields[c][1] == 2, f"PointCloud2 field {c!r} is {POINTFIELD_NAMES[fields[c][1]]}: expected UINT8")

    count = width * height
    buf = as_byte_array(msg.data, "PointCloud2 data")
    if count == 0:
        empty = np.zeros((0, 3))
        return PointCloudArrays(empty, np.zeros((0, 3), np.uint8) if (color_field or separate) else None, np.zeros(0, bool), (height, width), frame_id_of(msg))
    require(point_step > 0, f"PointCloud2 point_step must be positive, got {point_step}")
    row_bytes = width * point_step
    require(row_step >= row_bytes, f"PointCloud2 row_step {row_step} is smaller than width {width} x point_step {point_step}")
    rows = byte_rows(buf, height, row_step, row_bytes, f"PointCloud2 {width}x{height}")
    pts = rows.reshape(height * width, point_step)

    def column(name: str) -> np.ndarray:
        off, dt, _ = fields[name]
        dtype = np.dtype(POINTFIELD_DTYPES[dt]).newbyteorder(">" if big else "<")
        raw = np.ascontiguousarray(pts[:, off: off + dtype.itemsize])
        return raw.view(dtype).reshape(-1)

    xyz = np.stack([column(a).astype(np.float64) for a in ("x", "y", "z")], axis=1)
    _check_byte_order(xyz, fields, pts, big)
    valid = np.all(np.isfinite(xyz), axis=1) & np.any(xyz != 0.0, axis=1)
    xyz[~valid] = np.nan
    rgb = None
    if color_field:
        off = fields[color_field][0]
        packed = np.ascontiguousarray(pts[:, off: off + 4]).view(np.dtype(np.uint32).newbyteorder(">" if big else "<")).reshape(-1)
        packed = packed.astype(np.uint32)
        rgb = np.stack([(packed >> 16) & 0xFF, (packed >> 8) & 0xFF, packed & 0xFF], axis=1).astype(np.uint8)
    elif separate:
        rgb = np.stack([column(c) for c in ("r", "g", "b")], axis=1).astype(np.uint8)
    filled = None
    if FILLED_FIELD in fields and fields[FILLED_FIELD][1] == 2 and fields[FILLED_FIELD][0] + 1 <= point_step:
        filled = column(FILLED_FIELD) != 0
    return PointCloudArrays(xyz, rgb, valid, (height, width), frame_id_of(msg), filled)


def cloud_from_pointcloud2(msg: Any) -> CloudConversion:
    """The coloured cloud of a ``PointCloud2`` and its organized shape ``(H, W)`` (None if ``height == 1``).

    Unpacks as ``cloud, organized_shape = cloud_from_pointcloud2(msg)``; ``.has_color`` tells whether
    the message had colour (without it every point is grey 0.5).
    """
    arr = pointcloud2_to_arrays(msg)
    return CloudConversion(_valid_cloud(arr), arr.shape if arr.organized else None, arr.rgb is not None, arr)


def _valid_cloud(arr: PointCloudArrays) -> Cloud:
    """The cloud of the valid points (grey 0.5 without colour)."""
    pts = arr.xyz[arr.valid]
    colors = arr.rgb[arr.valid] if arr.rgb is not None else np.full((len(pts), 3), 0.5, dtype=np.float32)
    return Cloud(pts, colors, filled_mask=arr.filled[arr.valid] if arr.filled is not None else None)


def within_depth(conv: CloudConversion, max_depth: float) -> CloudConversion:
    """``conv`` with its points farther than ``max_depth`` (their z, in the optical frame) made invalid, as a
    driver's no return (``max_depth_m``; 0: unchanged)."""
    if not max_depth > 0:
        return conv
    arr = conv.arrays
    with np.errstate(invalid="ignore"):
        valid = arr.valid & ~(arr.xyz[:, 2] > max_depth)
    if valid.sum() == arr.valid.sum():
        return conv
    arrays = replace(arr, valid=valid)
    return CloudConversion(_valid_cloud(arrays), conv.organized_shape, conv.has_color, arrays)


def intrinsics_from_organized_cloud(arrays: PointCloudArrays, *, frame_id: str | None = None,
                                    max_rms_px: float = 0.75, min_points: int = 16) -> CameraIntrinsics:
    """Pinhole intrinsics of an organized cloud's grid by least squares.

    Point ``(row, col)`` of an organized cloud in its optical frame projects to pixel centre
    ``col = fx X/Z + cx`` and ``row = fy Y/Z + cy``; both lines are fitted. PwsError when too few
    points are valid or when the grid is not a pinhole image (RMS residual above ``max_rms_px``:
    e.g. a cloud transformed out of the camera frame).
    """
    H, W = arrays.shape
    require(H > 1, "intrinsics can be estimated only from an organized cloud (height > 1)")
    idx = np.nonzero(arrays.valid)[0]
    xyz = arrays.xyz[idx]
    front = xyz[:, 2] > 0
    idx, xyz = idx[front], xyz[front]
    require(len(idx) >= min_points, f"organized cloud has only {len(idx)} valid points in front of the camera; cannot estimate intrinsics (give a CameraInfo)")
    rows, cols = idx // W, idx % W
    out = []
    rms = []
    for coord, target in ((xyz[:, 0] / xyz[:, 2], cols), (xyz[:, 1] / xyz[:, 2], rows)):
        A = np.stack([coord, np.ones_like(coord)], axis=1)
        require(float(np.ptp(coord)) > 0, "organized cloud spans a single image column or row; cannot estimate intrinsics (give a CameraInfo)")
        sol, *_ = np.linalg.lstsq(A, target.astype(np.float64), rcond=None)
        res = A @ sol - target
        out.append(sol)
        rms.append(float(np.sqrt(np.mean(res * res))))
    (fx, cx), (fy, cy) = out
    require(fx > 0 and fy > 0, f"organized cloud is not a pinhole image grid (fitted fx={fx:.4g}, fy={fy:.4g}); is it in the camera optical frame? give a CameraInfo")
    require(max(rms) <= max_rms_px,
            f"organized cloud is not a pinhole image grid (fit residual {max(rms):.3g} px > {max_rms_px} px); is it in the camera optical frame? give a CameraInfo")
    return CameraIntrinsics(int(W), int(H), float(fx), float(fy), float(cx), float(cy), frame_id if frame_id is not None else arrays.frame_id)


def fill_organized(arrays: PointCloudArrays, intr: CameraIntrinsics, *, min_valid: float = 0.0) -> Cloud:
    """The cloud of an organized PointCloud2 whose invalid points are given a depth
    (:func:`~pws_ros.core.cloud.fill_depth`): a measured point keeps its coordinates, a filled one is
    back-projected through its pixel centre with ``intr`` at the filled depth; every point keeps the
    colour of its pixel (drivers send the colour of points without depth). Row-major order."""
    H, W = arrays.shape
    require((H, W) == intr.shape, f"organized PointCloud2 {W}x{H} and its camera {intr.width}x{intr.height} differ in size")
    z = arrays.xyz[:, 2].reshape(H, W)
    depth = np.where(arrays.valid.reshape(H, W) & (z > 0), z, np.nan)
    filled_depth, was_filled = fill_depth(depth, min_valid=min_valid)
    xyz = arrays.xyz.copy()
    rows, cols = np.nonzero(was_filled)
    zf = filled_depth[rows, cols]
    at = rows * W + cols
    xyz[at, 0] = (cols - intr.cx) * zf / intr.fx
    xyz[at, 1] = (rows - intr.cy) * zf / intr.fy
    xyz[at, 2] = zf
    keep = arrays.valid | was_filled.reshape(-1)
    colors = arrays.rgb[keep] if arrays.rgb is not None else np.full((int(keep.sum()), 3), 0.5, dtype=np.float32)
    return Cloud(xyz[keep], colors, filled_mask=was_filled.reshape(-1)[keep])


def cloud_and_intrinsics_from_pointcloud2(msg: Any, info_msg: Any | None = None, fallback: CameraIntrinsics | None = None, *,
                                          depth_fill: str = "off", min_valid: float = 0.0,
                                          max_depth: float = 0.0) -> tuple[Cloud, CameraIntrinsics, bool]:
    """The cloud of a PointCloud2 and the camera to render it with: ``(cloud, intrinsics, has_color)``.

    Intrinsics come from ``info_msg`` (an organized cloud must then have its size), else from the
    organized grid (least squares), else ``fallback``; an unorganized cloud without CameraInfo or
    fallback is refused. An organized cloud with ``depth_fill="row"`` has its invalid points filled
    (:func:`fill_organized`); ``min_valid``: the least share of valid points of an organized cloud;
    ``max_depth`` (> 0): points with a larger z are invalid (:func:`within_depth`).
    """
    require(depth_fill in DEPTH_FILLS, f"unknown depth_fill {depth_fill!r}: expected one of {', '.join(DEPTH_FILLS)}")
    conv = within_depth(cloud_from_pointcloud2(msg), max_depth)
    cloud, shape = conv
    frame = frame_id_of(msg)
    if info_msg is not None:
        intr = intrinsics_from_camera_info(info_msg)
        if shape is not None:
            require((intr.height, intr.width) == shape,
                    f"organized PointCloud2 {shape[1]}x{shape[0]} and CameraInfo {intr.width}x{intr.height} differ in size")
    elif shape is not None:
        intr = intrinsics_from_organized_cloud(conv.arrays, frame_id=frame)
    else:
        require(fallback is not None, "unorganized PointCloud2 (height 1) without a CameraInfo: set camera_info_topic or camera_info_file")
        intr = fallback
    if frame and not intr.frame_id:
        intr = replace(intr, frame_id=frame)
    if shape is not None:
        if depth_fill == "row":
            cloud = fill_organized(conv.arrays, intr, min_valid=min_valid)
        else:
            require_valid_share(conv.arrays.valid, min_valid, "the organized cloud's points have")
    return cloud, intr, conv.has_color


__all__ = ["CloudConversion", "POINTFIELD_DTYPES", "POINTFIELD_NAMES", "PointCloudArrays", "cloud_and_intrinsics_from_pointcloud2",
           "cloud_from_pointcloud2", "fill_organized", "intrinsics_from_organized_cloud", "pointcloud2_to_arrays", "within_depth"]
