"""Core objects -> ROS 2 messages, for any message-class namespace (rclpy or rosbags).

Builders take ``types``: a namespace whose attributes are message classes (``types.Image``,
``types.Header`` ...) plus three converters for array fields (``types.u8`` for ``uint8[]``,
``types.f64`` for ``float64[]``, ``types.f64fixed`` for ``float64[N]``), because rclpy and
rosbags want different Python types there. :func:`rosbags_types` builds it from a rosbags
typestore (tests, bag writing); :func:`pws_ros.nodes._ros.rclpy_types` from the installed ROS 2
message packages. Every field is passed as a keyword (rosbags constructors have no defaults;
fields a class does not know, e.g. newer ``Marker`` fields on an older distro, are left out).

Certification schema (``diagnostic_msgs/DiagnosticArray`` on ``certification``): header = the
source header; one ``DiagnosticStatus`` per axis named ``pws/<axis>`` with ``hardware_id`` = the
source frame id, ``level`` OK = certified, WARN = not certified or abstained, ERROR = could not
certify (``message`` says why), and ``values`` with exactly these keys first, in this order
(:data:`DIAGNOSTIC_KEYS`)::

    label class_name certified radius unit p_a_lower sigma n alpha num_partitions
    classifier_calls latency_ms compute_ms

followed by :data:`DIAGNOSTIC_EXTRA_KEYS`. ``p_a_lower`` is the smallest lower bound used.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np

from ..core.cloud import Cloud
from ..core.errors import PwsError, require
from ..core.motion import camera_pose
from ..core.result import STATUS_ABSTAIN, STATUS_CERTIFIED, STATUS_ERROR, STATUS_NOT_CERTIFIED, Certificate

DIAGNOSTIC_KEYS: tuple[str, ...] = (
    "label", "class_name", "certified", "radius", "unit", "p_a_lower", "sigma", "n", "alpha", "frame_alpha",
    "num_partitions", "classifier_calls", "latency_ms", "compute_ms",
)
DIAGNOSTIC_EXTRA_KEYS: tuple[str, ...] = (
    "status", "requested_radius", "method", "coverage", "n0", "delta_alpha", "num_bounds",
    "frames_rendered", "imaging", "reason", "node",
)
STATUS_NAME_PREFIX = "pws/"

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
    stamp_ns = int(stamp_ns)
    require(stamp_ns >= 0, f"stamp must be non-negative, got {stamp_ns} ns")
    return make(types.Time, sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)


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


def _identity_pose(types: Any, position: Sequence[float] = (0.0, 0.0, 0.0)) -> Any:
    return make_pose(types, np.eye(3), np.asarray(position, dtype=float))


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

    Unorganized (height 1) unless ``organized_shape`` ``(H, W)`` with ``H * W == len(cloud)``.
    """
    n = len(cloud)
    if organized_shape is not None:
        H, W = (int(v) for v in organized_shape)
        require(H * W == n, f"organized shape {W}x{H} does not hold {n} points")
    else:
        H, W = 1, n
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4")])
    pts = np.asarray(cloud.points)
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["rgb"] = pack_rgb(cloud.colors)
    fields = [make(types.PointField, name=name, offset=off, datatype=7, count=1)
              for name, off in (("x", 0), ("y", 4), ("z", 8), ("rgb", 12))]
    return make(types.PointCloud2, header=header, height=H, width=W, fields=fields, is_bigendian=False,
                point_step=16, row_step=16 * W, data=types.u8(rec.view(np.uint8).reshape(-1)),
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


# ---- certification ------------------------------------------------------------------------

LEVEL_FOR_STATUS = {STATUS_CERTIFIED: "OK", STATUS_NOT_CERTIFIED: "WARN", STATUS_ABSTAIN: "WARN", STATUS_ERROR: "ERROR"}


def level_value(types: Any, name: str) -> Any:
    """The class constant ``DiagnosticStatus.<name>`` (rclpy: a 1-byte ``bytes``; rosbags: int)."""
    return getattr(types.DiagnosticStatus, name)


def level_to_int(level: Any) -> int:
    if isinstance(level, (bytes, bytearray)):
        return int(level[0]) if len(level) else 0
    return int(level)


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return f"{v:.9g}"
    return str(v)


def _per_cert(value: Any, i: int, cert: Certificate, default: float) -> float:
    if value is None:
        return default
    if isinstance(value, dict):
        return float(value.get(cert.axis, default))
    if isinstance(value, (list, tuple, np.ndarray)):
        return float(value[i])
    return float(value)


def certificate_message(cert: Certificate) -> str:
    """The one-line ``DiagnosticStatus.message`` of a certificate."""
    if cert.status == STATUS_ERROR:
        return f"could not certify: {cert.reason or 'unknown error'}"
    if cert.status == STATUS_ABSTAIN:
        return "abstained: no class has p_A > 1/2 at the original pose" + (f" ({cert.reason})" if cert.reason else "")
    head = (f"{cert.class_name or cert.label} certified for ±{cert.requested_radius:.6g} {cert.unit}"
            if cert.certified else
            f"{cert.class_name or cert.label} not certified for ±{cert.requested_radius:.6g} {cert.unit} "
            f"(covered ±{cert.radius:.6g} {cert.unit})")
    return head + (f"; {cert.reason}" if cert.reason and not cert.certified else "")


def certificate_values(cert: Certificate, *, latency_ms: float, compute_ms: float, node_name: str = "") -> list[tuple[str, str]]:
    """The ``(key, value)`` pairs of one status: :data:`DIAGNOSTIC_KEYS` then the extras."""
    vals: list[tuple[str, Any]] = [
        ("label", int(cert.label)),
        ("class_name", cert.class_name),
        ("certified", bool(cert.certified)),
        ("radius", float(cert.radius)),
        ("unit", cert.unit),
        ("p_a_lower", float(cert.min_p_a_lower)),
        ("sigma", float(cert.sigma)),
        ("n", int(cert.n)),
        ("alpha", float(cert.alpha)),
        ("frame_alpha", float(cert.frame_alpha if cert.frame_alpha is not None else cert.alpha)),
        ("num_partitions", int(cert.num_partitions)),
        ("classifier_calls", int(cert.classifier_calls)),
        ("latency_ms", float(latency_ms)),
        ("compute_ms", float(compute_ms)),
        ("status", cert.status),
        ("requested_radius", float(cert.requested_radius)),
        ("method", cert.method),
        ("coverage", cert.coverage),
        ("n0", int(cert.n0)),
        ("delta_alpha", float(cert.delta_alpha)),
        ("num_bounds", int(cert.num_bounds)),
        ("frames_rendered", int(cert.frames_rendered)),
        ("imaging", cert.imaging),
        ("reason", " ".join(str(cert.reason).split())),
        ("node", node_name),
    ]
    return [(k, _fmt(v)) for k, v in vals]


def certificates_to_diagnostic_array(header: Any, certs: Sequence[Certificate], *, node_name: str, types: Any,
                                     latency_ms: float, compute_ms: Any = None) -> Any:
    """The ``certification`` message of one input frame (see the module docstring for the schema).

    ``header``: the source header (its ``frame_id`` becomes every status' ``hardware_id``);
    ``latency_ms``: node clock now minus the source stamp; ``compute_ms``: a number, a per-axis
    dict or sequence, or None for each certificate's ``timings['total']``.
    """
    statuses = []
    frame = str(getattr(header, "frame_id", "") or "")
    for i, cert in enumerate(certs):
        default_compute = 1000.0 * float(cert.timings.get("total", float("nan"))) if cert.timings else float("nan")
        cm = _per_cert(compute_ms, i, cert, default_compute)
        values = [make(types.KeyValue, key=k, value=v)
                  for k, v in certificate_values(cert, latency_ms=float(latency_ms), compute_ms=cm, node_name=node_name)]
        statuses.append(make(types.DiagnosticStatus, level=level_value(types, LEVEL_FOR_STATUS.get(cert.status, "ERROR")),
                             name=STATUS_NAME_PREFIX + cert.axis, message=certificate_message(cert),
                             hardware_id=frame, values=values))
    return make(types.DiagnosticArray, header=header, status=statuses)


def diagnostic_array_to_dicts(msg: Any) -> list[dict[str, Any]]:
    """Parse a DiagnosticArray: one dict per status with ``name``, ``level`` (int), ``message``,
    ``hardware_id``, ``keys`` (in message order) and ``values`` (key -> string)."""
    out = []
    for st in list(msg.status):
        keys = [str(kv.key) for kv in st.values]
        out.append({
            "name": str(st.name),
            "level": level_to_int(st.level),
            "message": str(st.message),
            "hardware_id": str(st.hardware_id),
            "keys": keys,
            "values": {str(kv.key): str(kv.value) for kv in st.values},
        })
    return out


def parse_certification(msg: Any) -> dict[str, dict[str, Any]]:
    """A ``certification`` message as ``{axis: {key: typed value}}`` (checks the key schema)."""
    out: dict[str, dict[str, Any]] = {}
    for st in diagnostic_array_to_dicts(msg):
        require(st["name"].startswith(STATUS_NAME_PREFIX), f"status {st['name']!r} is not a pws certification status")
        require(tuple(st["keys"][: len(DIAGNOSTIC_KEYS)]) == DIAGNOSTIC_KEYS,
                f"status {st['name']!r} keys {st['keys'][:len(DIAGNOSTIC_KEYS)]} do not follow the schema {list(DIAGNOSTIC_KEYS)}")
        v = st["values"]
        typed: dict[str, Any] = dict(v)
        for k in ("label", "n", "num_partitions", "classifier_calls", "n0", "num_bounds", "frames_rendered"):
            if k in v:
                typed[k] = int(v[k])
        for k in ("radius", "p_a_lower", "sigma", "alpha", "frame_alpha", "latency_ms", "compute_ms", "requested_radius",
                  "delta_alpha"):
            if k in v:
                typed[k] = float(v[k])
        typed["certified"] = v["certified"] == "true"
        typed["level"] = st["level"]
        typed["message"] = st["message"]
        typed["hardware_id"] = st["hardware_id"]
        out[st["name"][len(STATUS_NAME_PREFIX):]] = typed
    return out


# ---- RViz / Foxglove markers --------------------------------------------------------------

_LEVEL_COLORS = {"OK": (0.1, 0.9, 0.1), "WARN": (1.0, 0.8, 0.0), "ERROR": (1.0, 0.15, 0.15)}


def marker_text(cert: Certificate) -> str:
    if cert.status == STATUS_ERROR:
        return f"{cert.axis}: error ({cert.reason[:60]})"
    if cert.status == STATUS_ABSTAIN:
        return f"{cert.axis}: abstain"
    mark = "OK" if cert.certified else "NOT certified"
    return f"{cert.axis} ±{cert.requested_radius:.4g} {cert.unit}: {cert.class_name or cert.label} {mark} (p_A≥{cert.min_p_a_lower:.3f})"


def markers_for(header: Any, certs: Sequence[Certificate], types: Any, *, ns: str = "pws", text_height: float = 0.05,
                distance: float = 1.0, lifetime_s: float = 0.0) -> Any:
    """A ``MarkerArray`` of ``TEXT_VIEW_FACING`` markers (one line per axis, stacked downwards,
    ``distance`` metres in front of the camera in the source optical frame), coloured by level."""
    markers = []
    life = make(types.Duration, sec=int(lifetime_s), nanosec=int(round((lifetime_s % 1.0) * 1e9)))
    for i, cert in enumerate(certs):
        r, g, b = _LEVEL_COLORS[LEVEL_FOR_STATUS.get(cert.status, "ERROR")]
        kw: dict[str, Any] = dict(
            header=header, ns=ns, id=i, type=int(types.Marker.TEXT_VIEW_FACING), action=int(types.Marker.ADD),
            pose=_identity_pose(types, (0.0, -0.2 + 1.5 * text_height * i, float(distance))),
            scale=make(types.Vector3, x=0.0, y=0.0, z=float(text_height)),
            color=make(types.ColorRGBA, r=r, g=g, b=b, a=1.0), lifetime=life, frame_locked=False,
            points=[], colors=[], texture_resource="", uv_coordinates=[], text=marker_text(cert),
            mesh_resource="", mesh_use_embedded_materials=False,
        )
        if hasattr(types, "CompressedImage"):
            kw["texture"] = make(types.CompressedImage, header=make_header(types, 0, ""), format="", data=types.u8(np.zeros(0, np.uint8)))
        if hasattr(types, "MeshFile"):
            kw["mesh_file"] = make(types.MeshFile, filename="", data=types.u8(np.zeros(0, np.uint8)))
        markers.append(make(types.Marker, **kw))
    return make(types.MarkerArray, markers=markers)


# ---- health -------------------------------------------------------------------------------

def health_status(header: Any, *, node_name: str, types: Any, rate_hz: float, frames_in: int, frames_processed: int,
                  frames_dropped: int, device: str, last_error: str = "", warning: str = "",
                  extra: dict[str, Any] | None = None, activity: str = "processed") -> Any:
    """A ``/diagnostics`` DiagnosticArray with one status ``<node_name>: health``.

    Level ERROR when ``last_error`` is set, WARN when ``warning`` is set, else OK with the message
    ``"<frames_processed> frames <activity>, <frames_dropped> dropped"`` (activity: what the node does
    to a frame: certified, converted, planned, rendered). Keys: rate_hz, frames_in,
    frames_processed, frames_dropped, device, last_error, then ``extra``.
    """
    if last_error:
        level, message = "ERROR", " ".join(str(last_error).split())
    elif warning:
        level, message = "WARN", " ".join(str(warning).split())
    else:
        level, message = "OK", f"{frames_processed} frames {activity}, {frames_dropped} dropped"
    pairs: list[tuple[str, Any]] = [
        ("rate_hz", float(rate_hz)), ("frames_in", int(frames_in)), ("frames_processed", int(frames_processed)),
        ("frames_dropped", int(frames_dropped)), ("device", str(device)), ("last_error", " ".join(str(last_error).split())),
    ]
    pairs += list((extra or {}).items())
    values = [make(types.KeyValue, key=str(k), value=_fmt(v)) for k, v in pairs]
    st = make(types.DiagnosticStatus, level=level_value(types, level), name=f"{node_name}: health", message=message,
              hardware_id=str(getattr(header, "frame_id", "") or ""), values=values)
    return make(types.DiagnosticArray, header=header, status=[st])


__all__ = [
    "DIAGNOSTIC_EXTRA_KEYS", "DIAGNOSTIC_KEYS", "LEVEL_FOR_STATUS", "MESSAGE_TYPES", "camera_info_from_intrinsics",
    "certificate_message", "certificate_values", "certificates_to_diagnostic_array", "cloud_to_pointcloud2", "copy_header",
    "diagnostic_array_to_dicts", "health_status", "image_from_numpy", "level_to_int", "make", "make_header", "make_pose",
    "make_time", "markers_for", "pack_rgb", "parse_certification", "plan_to_pose_array", "quaternion_from_matrix",
    "rosbags_types",
]
