"""ROS 2 messages -> numpy arrays and core objects (duck-typed: rclpy or rosbags messages).

Only the field names of ``sensor_msgs`` are used, so the same functions convert live rclpy messages
in the nodes and recorded rosbags messages in tests and ``pws replay``. Every malformed input raises
:class:`~pws_ros.core.errors.PwsError` with a one-line message saying what is wrong.

Conventions
-----------
- Colour images (``rgb8 bgr8 rgba8 bgra8 mono8``) become ``(H, W, 3)`` uint8 **RGB**.
- Depth images (``16UC1``/``mono16`` in millimetres, ``32FC1`` in metres) become ``(H, W)``
  arrays in their own unit (:func:`image_to_numpy`) or metres with NaN for invalid pixels
  (:func:`depth_to_meters`; 0, NaN, inf and negative values are invalid).
- Row padding (``step`` larger than ``width * bytes_per_pixel``) and ``is_bigendian`` are honoured.
- A ``PointCloud2`` needs ``x, y, z`` (float32 or float64, any offsets); colour is optional: a
  packed ``rgb``/``rgba`` field (float32 or uint32/int32 holding ``0x00RRGGBB``) or separate
  ``r, g, b`` uint8 fields. Points with a non-finite coordinate, or exactly at the origin (the
  "no return" marker of several drivers), are dropped.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.cloud import Cloud
from ..core.cloud import cloud_from_rgbd as _core_cloud_from_rgbd
from ..core.errors import PwsError, require
from ..core.registration import Extrinsic, register_depth

# encoding -> (channels, numpy dtype, bytes per channel)
COLOR_ENCODINGS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}
DEPTH_ENCODINGS = {"16uc1": np.uint16, "mono16": np.uint16, "32fc1": np.float32}
# Images this module builds but does not read as camera input (used by the four-process scheme).
FLOAT_ENCODINGS = {"32fc3": 3, "32fc1": 1}
SUPPORTED_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "16UC1", "mono16", "32FC1", "32FC3")

ALIGNED_DEPTH_HINT = "use an aligned depth topic such as /camera/aligned_depth_to_color/image_raw"

# sensor_msgs/PointField datatypes
POINTFIELD_DTYPES = {1: np.int8, 2: np.uint8, 3: np.int16, 4: np.uint16, 5: np.int32, 6: np.uint32, 7: np.float32, 8: np.float64}
POINTFIELD_NAMES = {1: "INT8", 2: "UINT8", 3: "INT16", 4: "UINT16", 5: "INT32", 6: "UINT32", 7: "FLOAT32", 8: "FLOAT64"}


# ---- helpers ------------------------------------------------------------------------------

def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (``sec``, ``nanosec``) as integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def header_stamp_ns(msg: Any) -> int:
    """Stamp of a message with a ``header`` in nanoseconds."""
    return stamp_to_ns(msg.header.stamp)


def _frame_id(msg: Any) -> str:
    header = getattr(msg, "header", None)
    return str(getattr(header, "frame_id", "") or "")


def as_byte_array(data: Any, what: str = "data") -> np.ndarray:
    """A message's ``uint8[]`` field as a flat read-only uint8 numpy array (no copy when possible).

    Accepts numpy arrays (rosbags), ``array.array('B')`` (rclpy), ``bytes``/``bytearray``/
    ``memoryview`` and plain sequences of ints.
    """
    if isinstance(data, np.ndarray):
        if data.dtype == np.uint8:
            return data.reshape(-1)
        require(data.dtype.itemsize == 1, f"{what} must be bytes, got an array of {data.dtype}")
        return data.reshape(-1).view(np.uint8)
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=np.uint8)
    try:
        mv = memoryview(data)  # array.array('B') and other buffers
    except TypeError:
        try:
            return np.asarray(data, dtype=np.uint8).reshape(-1)
        except (TypeError, ValueError, OverflowError) as exc:
            raise PwsError(f"{what} is not a byte sequence ({exc})") from None
    require(mv.itemsize == 1, f"{what} must be bytes, got items of {mv.itemsize} bytes")
    return np.frombuffer(mv, dtype=np.uint8)


def _positive_int(value: Any, what: str) -> int:
    try:
        out = int(value)
    except (TypeError, ValueError):
        raise PwsError(f"{what} must be an integer, got {value!r}") from None
    require(out > 0, f"{what} must be positive, got {out}")
    return out


def _rows(buf: np.ndarray, height: int, step: int, row_bytes: int, what: str) -> np.ndarray:
    """``(height, row_bytes)`` uint8 view of a row-padded buffer (the last row's padding may be absent)."""
    require(step >= row_bytes, f"{what}: step {step} is smaller than one row of pixels ({row_bytes} bytes)")
    need = step * (height - 1) + row_bytes
    require(buf.size >= need, f"{what}: data has {buf.size} bytes, expected at least {need} (step {step} x height {height}): truncated message")
    if buf.size >= step * height:
        return buf[: step * height].reshape(height, step)[:, :row_bytes]
    # last row without its padding
    padded = np.zeros(step * height, dtype=np.uint8)
    padded[: buf.size] = buf
    return padded.reshape(height, step)[:, :row_bytes]


def _encoding(msg: Any) -> str:
    enc = str(getattr(msg, "encoding", "") or "").strip()
    require(enc != "", "Image has an empty encoding")
    return enc


# ---- images -------------------------------------------------------------------------------

def image_to_numpy(msg: Any) -> np.ndarray:
    """A ``sensor_msgs/Image`` as a numpy array.

    Colour encodings give ``(H, W, 3)`` uint8 RGB (alpha dropped, BGR swapped, mono replicated);
    depth encodings give ``(H, W)`` uint16 (``16UC1``/``mono16``, native byte order) or float32
    (``32FC1``); ``32FC3`` gives ``(H, W, 3)`` float32. The result owns its memory.
    """
    enc = _encoding(msg)
    key = enc.lower()
    width = _positive_int(getattr(msg, "width", 0), "Image width")
    height = _positive_int(getattr(msg, "height", 0), "Image height")
    step = int(getattr(msg, "step", 0))
    big = bool(getattr(msg, "is_bigendian", 0))
    buf = as_byte_array(msg.data, "Image data")
    if key in COLOR_ENCODINGS:
        ch = COLOR_ENCODINGS[key]
        rows = _rows(buf, height, step, width * ch, f"{enc} Image {width}x{height}")
        img = rows.reshape(height, width, ch)
        if key == "mono8":
            return np.repeat(img, 3, axis=2)
        if key in ("bgr8", "bgra8"):
            return np.ascontiguousarray(img[:, :, 2::-1])
        return np.ascontiguousarray(img[:, :, :3])
    if key in DEPTH_ENCODINGS:
        dt = np.dtype(DEPTH_ENCODINGS[key]).newbyteorder(">" if big else "<")
        rows = _rows(buf, height, step, width * dt.itemsize, f"{enc} Image {width}x{height}")
        out = np.ascontiguousarray(rows).view(dt).reshape(height, width)
        return out.astype(DEPTH_ENCODINGS[key])  # native byte order, own memory
    if key in FLOAT_ENCODINGS:
        ch = FLOAT_ENCODINGS[key]
        dt = np.dtype(np.float32).newbyteorder(">" if big else "<")
        rows = _rows(buf, height, step, width * ch * 4, f"{enc} Image {width}x{height}")
        out = np.ascontiguousarray(rows).view(dt).reshape(height, width, ch) if ch > 1 else np.ascontiguousarray(rows).view(dt).reshape(height, width)
        return out.astype(np.float32)
    raise PwsError(f"unsupported image encoding {enc!r}: expected one of {', '.join(SUPPORTED_ENCODINGS)}")


def color_to_numpy(msg: Any) -> np.ndarray:
    """A colour ``Image`` as ``(H, W, 3)`` uint8 RGB; PwsError for a depth or float encoding."""
    key = _encoding(msg).lower()
    require(key in COLOR_ENCODINGS,
            f"colour image has encoding {msg.encoding!r}: expected one of rgb8, bgr8, rgba8, bgra8, mono8")
    return image_to_numpy(msg)


def depth_to_meters(msg: Any) -> np.ndarray:
    """A depth ``Image`` as ``(H, W)`` float64 metres; invalid pixels (0, NaN, inf, < 0) are NaN.

    ``16UC1``/``mono16`` are millimetres, ``32FC1`` metres (REP 118).
    """
    key = _encoding(msg).lower()
    require(key in DEPTH_ENCODINGS,
            f"depth image has encoding {msg.encoding!r}: expected 16UC1 or mono16 (millimetres) or 32FC1 (metres)")
    raw = image_to_numpy(msg)
    if raw.dtype == np.uint16:
        depth = raw.astype(np.float64) / 1000.0
    else:
        depth = raw.astype(np.float64)
    with np.errstate(invalid="ignore"):
        invalid = ~np.isfinite(depth) | (depth <= 0)
    depth[invalid] = np.nan
    return depth


# ---- camera info --------------------------------------------------------------------------

def intrinsics_from_camera_info(msg: Any) -> CameraIntrinsics:
    """Pinhole intrinsics of a ``sensor_msgs/CameraInfo`` (K; binning and ROI must be unused)."""
    bx, by = int(getattr(msg, "binning_x", 0) or 0), int(getattr(msg, "binning_y", 0) or 0)
    require(bx <= 1 and by <= 1, f"CameraInfo uses binning {bx}x{by}, which is not supported; publish the binned camera's own CameraInfo")
    roi = getattr(msg, "roi", None)
    if roi is not None:
        rw, rh = int(getattr(roi, "width", 0) or 0), int(getattr(roi, "height", 0) or 0)
        full = (rw == 0 and rh == 0) or (rw == int(msg.width) and rh == int(msg.height))
        require(full, f"CameraInfo has a region of interest {rw}x{rh} of a {int(msg.width)}x{int(msg.height)} camera, which is not supported")
    require(int(msg.width) > 0 and int(msg.height) > 0, f"CameraInfo has no image size ({int(msg.width)}x{int(msg.height)})")
    return CameraIntrinsics.from_camera_info(msg)


def _same_intrinsics(a: CameraIntrinsics, b: CameraIntrinsics, rtol: float = 1e-4) -> bool:
    return (a.width, a.height) == (b.width, b.height) and all(
        math.isclose(getattr(a, k), getattr(b, k), rel_tol=rtol, abs_tol=1e-3) for k in ("fx", "fy", "cx", "cy"))


# ---- point clouds -------------------------------------------------------------------------

@dataclass
class PointCloudArrays:
    """Every point of a PointCloud2 in message order: ``xyz`` (M, 3) float64 with NaN where invalid,
    ``rgb`` (M, 3) uint8 (or None without colour), ``valid`` (M,) bool, ``shape`` (H, W)."""

    xyz: np.ndarray
    rgb: np.ndarray | None
    valid: np.ndarray
    shape: tuple[int, int]
    frame_id: str = ""

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
        return PointCloudArrays(empty, np.zeros((0, 3), np.uint8) if (color_field or separate) else None, np.zeros(0, bool), (height, width), _frame_id(msg))
    require(point_step > 0, f"PointCloud2 point_step must be positive, got {point_step}")
    row_bytes = width * point_step
    require(row_step >= row_bytes, f"PointCloud2 row_step {row_step} is smaller than width {width} x point_step {point_step}")
    rows = _rows(buf, height, row_step, row_bytes, f"PointCloud2 {width}x{height}")
    pts = rows.reshape(height * width, point_step)

    def column(name: str) -> np.ndarray:
        off, dt, _ = fields[name]
        dtype = np.dtype(POINTFIELD_DTYPES[dt]).newbyteorder(">" if big else "<")
        raw = np.ascontiguousarray(pts[:, off: off + dtype.itemsize])
        return raw.view(dtype).reshape(-1)

    xyz = np.stack([column(a).astype(np.float64) for a in ("x", "y", "z")], axis=1)
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
    return PointCloudArrays(xyz, rgb, valid, (height, width), _frame_id(msg))


def cloud_from_pointcloud2(msg: Any) -> CloudConversion:
    """The coloured cloud of a ``PointCloud2`` and its organized shape ``(H, W)`` (None if ``height == 1``).

    Unpacks as ``cloud, organized_shape = cloud_from_pointcloud2(msg)``; ``.has_color`` tells whether
    the message had colour (without it every point is grey 0.5).
    """
    arr = pointcloud2_to_arrays(msg)
    pts = arr.xyz[arr.valid]
    if arr.rgb is not None:
        colors = arr.rgb[arr.valid]
    else:
        colors = np.full((len(pts), 3), 0.5, dtype=np.float32)
    cloud = Cloud(pts, colors)
    return CloudConversion(cloud, arr.shape if arr.organized else None, arr.rgb is not None, arr)


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


def cloud_and_intrinsics_from_pointcloud2(msg: Any, info_msg: Any | None = None,
                                          fallback: CameraIntrinsics | None = None) -> tuple[Cloud, CameraIntrinsics, bool]:
    """The cloud of a PointCloud2 and the camera to render it with: ``(cloud, intrinsics, has_color)``.

    Intrinsics come from ``info_msg`` (an organized cloud must then have its size), else from the
    organized grid (least squares), else ``fallback``; an unorganized cloud without CameraInfo or
    fallback is refused.
    """
    conv = cloud_from_pointcloud2(msg)
    cloud, shape = conv
    frame = _frame_id(msg)
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
    return cloud, intr, conv.has_color


# ---- RGB-D --------------------------------------------------------------------------------

def extrinsic_from_transform(msg: Any, source: str = "") -> Extrinsic:
    """A ``geometry_msgs/Transform`` (or the ``transform`` of a ``TransformStamped``) as an
    :class:`~pws_ros.core.registration.Extrinsic` (PwsError when malformed)."""
    tf = getattr(msg, "transform", msg)
    try:
        tr, q = tf.translation, tf.rotation
        return Extrinsic.from_quaternion((q.x, q.y, q.z, q.w), (tr.x, tr.y, tr.z), source)
    except AttributeError as exc:
        raise PwsError(f"not a geometry_msgs/Transform ({exc})") from None


def transforms_from_tf_message(msg: Any) -> list[tuple[str, str, Extrinsic]]:
    """The ``(parent, child, T)`` edges of a ``tf2_msgs/TFMessage`` (``/tf_static``), ``T`` mapping child
    coordinates to parent coordinates, frame names without a leading ``/``: the input of
    :func:`~pws_ros.core.registration.chain_transform`."""
    edges = []
    for ts in list(getattr(msg, "transforms", []) or []):
        parent, child = str(ts.header.frame_id).lstrip("/"), str(ts.child_frame_id).lstrip("/")
        edges.append((parent, child, extrinsic_from_transform(ts, f"{parent} <- {child}")))
    return edges


def registration_problem(depth_msg: Any, color_msg: Any, info_msg: Any, depth_info_msg: Any | None = None,
                         *, require_same_frame: bool = True) -> str:
    """Why a depth + colour pair is not registered ("" when it is, as far as the messages tell):
    different image sizes, a depth CameraInfo whose intrinsics differ from ``info_msg``'s, or (with
    ``require_same_frame``) different non-empty ``frame_id`` s. Reads only sizes and headers."""
    dw, dh = int(getattr(depth_msg, "width", 0)), int(getattr(depth_msg, "height", 0))
    cw, ch = int(getattr(color_msg, "width", 0)), int(getattr(color_msg, "height", 0))
    if (dh, dw) != (ch, cw):
        return f"depth {dw}x{dh} and colour {cw}x{ch} are not registered (different sizes)"
    if depth_info_msg is not None:
        dintr, intr = intrinsics_from_camera_info(depth_info_msg), intrinsics_from_camera_info(info_msg)
        if not _same_intrinsics(dintr, intr):
            return (f"depth and colour are not registered (depth camera fx={dintr.fx:.1f} cx={dintr.cx:.1f} {dintr.width}x{dintr.height}, "
                    f"colour camera fx={intr.fx:.1f} cx={intr.cx:.1f} {intr.width}x{intr.height})")
    dframe, cframe = _frame_id(depth_msg), _frame_id(color_msg)
    if require_same_frame and dframe and cframe and dframe != cframe:
        return f"depth frame {dframe!r} and colour frame {cframe!r} differ: depth and colour are not registered"
    return ""


def cloud_from_rgbd(depth_msg: Any, color_msg: Any, info_msg: Any, depth_info_msg: Any | None = None,
                    *, require_same_frame: bool = True, extrinsic: Extrinsic | None = None) -> tuple[Cloud, CameraIntrinsics]:
    """The one-frame cloud of a depth + colour pair and the colour camera's intrinsics.

    Depth and colour must be *registered* (the depth resampled into the colour camera): same size
    as each other and as ``info_msg``; when ``depth_info_msg`` (the depth stream's own CameraInfo)
    is given its intrinsics must equal ``info_msg``'s; with ``require_same_frame`` non-empty
    ``frame_id`` s must agree (:func:`registration_problem`). A pair that is not registered is
    registered here when ``extrinsic`` (depth -> colour optical frame) and ``depth_info_msg`` are
    given (:func:`~pws_ros.core.registration.register_depth`: nearest depth wins, holes stay holes);
    otherwise PwsError: such data would paint points with the wrong colours.
    """
    problem = registration_problem(depth_msg, color_msg, info_msg, depth_info_msg, require_same_frame=require_same_frame)
    require(not problem or extrinsic is not None, f"{problem}; {ALIGNED_DEPTH_HINT}")
    depth = depth_to_meters(depth_msg)
    rgb = color_to_numpy(color_msg)
    ch, cw = rgb.shape[:2]
    intr = intrinsics_from_camera_info(info_msg)
    require((intr.height, intr.width) == (ch, cw),
            f"CameraInfo {intr.width}x{intr.height} does not match the images {cw}x{ch}; use the colour camera's CameraInfo")
    if problem:
        require(depth_info_msg is not None,
                f"{problem}; registering depth into the colour camera needs the depth camera's CameraInfo (depth_camera_info_topic)")
        dintr = intrinsics_from_camera_info(depth_info_msg)
        require(dintr.shape == depth.shape,
                f"depth CameraInfo {dintr.width}x{dintr.height} does not match the depth image {depth.shape[1]}x{depth.shape[0]}")
        depth = register_depth(depth, dintr, intr, extrinsic)
    cframe = _frame_id(color_msg)
    if cframe and not intr.frame_id:
        intr = replace(intr, frame_id=cframe)
    return _core_cloud_from_rgbd(depth, rgb, intr), intr


__all__ = [
    "ALIGNED_DEPTH_HINT", "CloudConversion", "PointCloudArrays", "SUPPORTED_ENCODINGS", "as_byte_array",
    "cloud_and_intrinsics_from_pointcloud2", "cloud_from_pointcloud2", "cloud_from_rgbd", "color_to_numpy",
    "depth_to_meters", "extrinsic_from_transform", "header_stamp_ns", "image_to_numpy", "intrinsics_from_camera_info",
    "intrinsics_from_organized_cloud", "pointcloud2_to_arrays", "registration_problem", "stamp_to_ns", "transforms_from_tf_message",
]
