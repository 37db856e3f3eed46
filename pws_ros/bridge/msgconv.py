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
- ``PointCloud2`` decoding is :mod:`pws_ros.bridge.cloudconv`.
"""
from __future__ import annotations

import math
from dataclasses import replace
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


# ---- helpers ------------------------------------------------------------------------------

def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (``sec``, ``nanosec``) as integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def header_stamp_ns(msg: Any) -> int:
    """Stamp of a message with a ``header`` in nanoseconds."""
    return stamp_to_ns(msg.header.stamp)


def frame_id_of(msg: Any) -> str:
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


def byte_rows(buf: np.ndarray, height: int, step: int, row_bytes: int, what: str) -> np.ndarray:
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
        rows = byte_rows(buf, height, step, width * ch, f"{enc} Image {width}x{height}")
        img = rows.reshape(height, width, ch)
        if key == "mono8":
            return np.repeat(img, 3, axis=2)
        if key in ("bgr8", "bgra8"):
            return np.ascontiguousarray(img[:, :, 2::-1])
        return np.ascontiguousarray(img[:, :, :3])
    if key in DEPTH_ENCODINGS:
        dt = np.dtype(DEPTH_ENCODINGS[key]).newbyteorder(">" if big else "<")
        rows = byte_rows(buf, height, step, width * dt.itemsize, f"{enc} Image {width}x{height}")
        out = np.ascontiguousarray(rows).view(dt).reshape(height, width)
        return out.astype(DEPTH_ENCODINGS[key])  # native byte order, own memory
    if key in FLOAT_ENCODINGS:
        ch = FLOAT_ENCODINGS[key]
        dt = np.dtype(np.float32).newbyteorder(">" if big else "<")
        rows = byte_rows(buf, height, step, width * ch * 4, f"{enc} Image {width}x{height}")
        out = np.ascontiguousarray(rows).view(dt).reshape(height, width, ch) if ch > 1 else np.ascontiguousarray(rows).view(dt).reshape(height, width)
        return out.astype(np.float32)
    raise PwsError(f"unsupported image encoding {enc!r}: expected one of {', '.join(SUPPORTED_ENCODINGS)}")


def color_to_numpy(msg: Any) -> np.ndarray:
    """A colour ``Image`` as ``(H, W, 3)`` uint8 RGB; PwsError for a depth or float encoding."""
    key = _encoding(msg).lower()
    require(key in COLOR_ENCODINGS,
            f"colour image has encoding {msg.encoding!r}: expected one of rgb8, bgr8, rgba8, bgra8, mono8")
    return image_to_numpy(msg)


def depth_to_meters(msg: Any, max_depth: float = 0.0) -> np.ndarray:
    """A depth ``Image`` as ``(H, W)`` float64 metres; invalid pixels (0, NaN, inf, < 0, and farther than
    ``max_depth`` when it is > 0: ``max_depth_m``) are NaN.

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
        if max_depth > 0:
            invalid |= depth > max_depth
    depth[invalid] = np.nan
    return depth


# ---- camera info --------------------------------------------------------------------------

# distortion models of sensor_msgs/distortion_models.hpp (and "" for none)
KNOWN_DISTORTION_MODELS = ("", "plumb_bob", "rational_polynomial", "equidistant")
MAX_CAMERA_SIDE = 16384   # px: a CameraInfo larger than this is refused (it sizes arrays; no camera is that large)


def _array_field(msg: Any, name: str) -> Any:
    value = getattr(msg, name, None)
    return [] if value is None else value


def _finite_numbers(values: Any, what: str) -> np.ndarray:
    """A CameraInfo array field as float64, PwsError naming the first NaN or inf entry."""
    try:
        arr = np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise PwsError(f"CameraInfo {what} is not a sequence of numbers") from None
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        raise PwsError(f"CameraInfo {what}[{int(bad[0])}] is {arr[bad[0]]}: every {what} coefficient must be finite")
    return arr


def distortion_note(msg: Any) -> str:
    """What the imaging does with a CameraInfo's distortion ("" when there is nothing to say): it takes
    every image as rectified (pinhole, no distortion), so an unknown model, or non-zero coefficients,
    mean the certified frames are not exactly the camera's images."""
    model = str(getattr(msg, "distortion_model", "") or "")
    try:
        d = np.asarray(_array_field(msg, "d"), dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return ""  # refused with its reason by intrinsics_from_camera_info
    if model not in KNOWN_DISTORTION_MODELS:
        return (f"CameraInfo distortion model {model[:40]!r} is not one of {', '.join(m for m in KNOWN_DISTORTION_MODELS if m)}: "
                "its coefficients are ignored; the imaging takes the images as rectified (pinhole, no distortion)")
    if d.size and np.isfinite(d).all() and np.any(d != 0):
        return (f"CameraInfo has non-zero {model} distortion coefficients: the imaging takes the images as rectified "
                "(pinhole, no distortion); certify rectified images (image_proc) for frames that match the camera")
    return ""


def intrinsics_from_camera_info(msg: Any) -> CameraIntrinsics:
    """Pinhole intrinsics of a ``sensor_msgs/CameraInfo`` (K; binning and ROI must be unused; K and the
    distortion coefficients D finite; at most ``MAX_CAMERA_SIDE`` px a side). The distortion is not
    modelled: images are taken as rectified (:func:`distortion_note` says what that ignores)."""
    _finite_numbers(_array_field(msg, "k"), "K")
    _finite_numbers(_array_field(msg, "d"), "D")
    try:
        w, h = int(msg.width), int(msg.height)
    except (TypeError, ValueError, OverflowError):
        raise PwsError("CameraInfo has a malformed image size") from None
    require(w <= MAX_CAMERA_SIDE and h <= MAX_CAMERA_SIDE, f"CameraInfo size {w}x{h} is above {MAX_CAMERA_SIDE} px a side")
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
    dframe, cframe = frame_id_of(depth_msg), frame_id_of(color_msg)
    if require_same_frame and dframe and cframe and dframe != cframe:
        return f"depth frame {dframe!r} and colour frame {cframe!r} differ: depth and colour are not registered"
    return ""


def cloud_from_rgbd(depth_msg: Any, color_msg: Any, info_msg: Any, depth_info_msg: Any | None = None,
                    *, require_same_frame: bool = True, extrinsic: Extrinsic | None = None, depth_fill: str = "off",
                    min_valid: float = 0.0, max_depth: float = 0.0) -> tuple[Cloud, CameraIntrinsics]:
    """The one-frame cloud of a depth + colour pair and the colour camera's intrinsics.

    Depth and colour must be *registered* (the depth resampled into the colour camera): same size
    as each other and as ``info_msg``; when ``depth_info_msg`` (the depth stream's own CameraInfo)
    is given its intrinsics must equal ``info_msg``'s; with ``require_same_frame`` non-empty
    ``frame_id`` s must agree (:func:`registration_problem`). A pair that is not registered is
    registered here when ``extrinsic`` (depth -> colour optical frame) and ``depth_info_msg`` are
    given (:func:`~pws_ros.core.registration.register_depth`: nearest depth wins, holes stay holes);
    otherwise PwsError: such data would paint points with the wrong colours. ``depth_fill`` and
    ``min_valid``: see :func:`~pws_ros.core.cloud.cloud_from_rgbd` (applied in the colour camera);
    ``max_depth`` (> 0): depth beyond it is invalid (:func:`depth_to_meters`, in the depth camera).
    """
    problem = registration_problem(depth_msg, color_msg, info_msg, depth_info_msg, require_same_frame=require_same_frame)
    require(not problem or extrinsic is not None, f"{problem}; {ALIGNED_DEPTH_HINT}")
    depth = depth_to_meters(depth_msg, max_depth)
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
    cframe = frame_id_of(color_msg)
    if cframe and not intr.frame_id:
        intr = replace(intr, frame_id=cframe)
    return _core_cloud_from_rgbd(depth, rgb, intr, fill=depth_fill, min_valid=min_valid), intr


__all__ = [
    "ALIGNED_DEPTH_HINT", "SUPPORTED_ENCODINGS", "as_byte_array", "byte_rows", "cloud_from_rgbd", "color_to_numpy",
    "depth_to_meters", "distortion_note", "extrinsic_from_transform", "KNOWN_DISTORTION_MODELS", "MAX_CAMERA_SIDE",
    "frame_id_of", "header_stamp_ns", "image_to_numpy", "intrinsics_from_camera_info",
    "registration_problem", "stamp_to_ns", "transforms_from_tf_message",
]
