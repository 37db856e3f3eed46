"""Record views of the procedural world as a rosbag2 bag (MCAP or sqlite3), like an RGB-D driver.

Topics (all messages of one frame share one header stamp, frame_id ``camera_color_optical_frame``):

* ``/camera/color/image_raw``                  sensor_msgs/Image, rgb8
* ``/camera/color/camera_info``                sensor_msgs/CameraInfo, plumb_bob, d = 0
* ``/camera/aligned_depth_to_color/image_raw`` sensor_msgs/Image, 16UC1 millimetres, 0 = invalid
* ``/camera/depth/color/points``               sensor_msgs/PointCloud2, organized HxW, x y z rgb
  (float32 at 0, 4, 8, 12; point_step 16), NaN xyz where invalid, is_dense false
* ``/pws/ground_truth``                        diagnostic_msgs/DiagnosticArray with one status
  ``ground_truth`` whose values are label, class_name, scene_seed, view_index, ... : enough to
  regenerate the dense cloud with :func:`pws_ros.sim.dense_cloud_for`.

``record(..., points=False)`` (``pws sim record --no-points``) leaves the PointCloud2 out: at 640x480
it is 4.9 MB a frame (16 B a point) and holds nothing the depth image and CameraInfo do not.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.errors import PwsError, require
from .objects import CLASS_NAMES
from .poses import NUM_VIEWS
from .world import FRAME_ID, View, render_view

TOPIC_COLOR = "/camera/color/image_raw"
TOPIC_INFO = "/camera/color/camera_info"
TOPIC_DEPTH = "/camera/aligned_depth_to_color/image_raw"
TOPIC_POINTS = "/camera/depth/color/points"
TOPIC_TRUTH = "/pws/ground_truth"
TOPICS = {
    TOPIC_COLOR: "sensor_msgs/msg/Image",
    TOPIC_INFO: "sensor_msgs/msg/CameraInfo",
    TOPIC_DEPTH: "sensor_msgs/msg/Image",
    TOPIC_POINTS: "sensor_msgs/msg/PointCloud2",
    TOPIC_TRUTH: "diagnostic_msgs/msg/DiagnosticArray",
}
START_NS = 1_700_000_000 * 10**9
STORAGES = ("mcap", "sqlite3")
TOPICS_WITHOUT_POINTS = {t: ty for t, ty in TOPICS.items() if t != TOPIC_POINTS}


def frame_schedule(frames: int, seed: int = 0, views_per_scene: int = 3) -> list[tuple[int, int]]:
    """``(scene_seed, view_index)`` of each frame: consecutive scenes ``seed, seed+1, ...`` (so
    consecutive classes), ``views_per_scene`` views each, spread over the rings and azimuths."""
    require(int(frames) > 0, f"frames must be positive, got {frames}")
    require(int(seed) >= 0, f"seed must be >= 0, got {seed}")
    require(1 <= int(views_per_scene) <= NUM_VIEWS, f"views_per_scene must be in [1, {NUM_VIEWS}], got {views_per_scene}")
    out = []
    for i in range(int(frames)):
        k, j = divmod(i, int(views_per_scene))
        scene = int(seed) + k
        view = (scene * 5 + j * 11) % NUM_VIEWS
        out.append((scene, view))
    return out


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """uint8 (..., 3) -> float32 (...) with the bits of ``r << 16 | g << 8 | b`` (PCL packing)."""
    rgb = np.asarray(rgb, dtype=np.uint32)
    return ((rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]).astype(np.uint32).view(np.float32)


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    p = np.ascontiguousarray(packed, dtype=np.float32).view(np.uint32)
    return np.stack([(p >> 16) & 255, (p >> 8) & 255, p & 255], axis=-1).astype(np.uint8)


def organized_points(view: View) -> np.ndarray:
    """(H, W, 4) float32 x, y, z, packed rgb; NaN xyz where the depth is invalid."""
    intr = view.intrinsics
    H, W = intr.shape
    depth = view.depth.astype(np.float64)
    valid = depth > 0
    rows, cols = np.mgrid[0:H, 0:W]
    z = np.where(valid, depth, np.nan)
    x = (cols - intr.cx) * z / intr.fx
    y = (rows - intr.cy) * z / intr.fy
    out = np.empty((H, W, 4), dtype=np.float32)
    out[..., 0], out[..., 1], out[..., 2] = x, y, z
    out[..., 3] = pack_rgb(view.rgb)
    return out


def depth_to_mm(depth_m: np.ndarray) -> np.ndarray:
    mm = np.round(np.asarray(depth_m, dtype=np.float64) * 1000.0)
    return np.where((mm > 0) & (mm <= 65535), mm, 0).astype(np.uint16)


class _Msgs:
    """Builds rosbags messages of the ros2_jazzy typestore."""

    def __init__(self):
        from rosbags.typesys import Stores, get_typestore

        self.ts = get_typestore(Stores.ROS2_JAZZY)
        t = self.ts.types
        self.Time = t["builtin_interfaces/msg/Time"]
        self.Header = t["std_msgs/msg/Header"]
        self.Image = t["sensor_msgs/msg/Image"]
        self.CameraInfo = t["sensor_msgs/msg/CameraInfo"]
        self.ROI = t["sensor_msgs/msg/RegionOfInterest"]
        self.PointCloud2 = t["sensor_msgs/msg/PointCloud2"]
        self.PointField = t["sensor_msgs/msg/PointField"]
        self.DiagnosticArray = t["diagnostic_msgs/msg/DiagnosticArray"]
        self.DiagnosticStatus = t["diagnostic_msgs/msg/DiagnosticStatus"]
        self.KeyValue = t["diagnostic_msgs/msg/KeyValue"]

    def header(self, stamp_ns: int):
        return self.Header(stamp=self.Time(sec=int(stamp_ns // 10**9), nanosec=int(stamp_ns % 10**9)), frame_id=FRAME_ID)

    def image(self, stamp_ns, arr: np.ndarray, encoding: str):
        arr = np.ascontiguousarray(arr)
        H, W = arr.shape[:2]
        step = arr.strides[0]
        return self.Image(header=self.header(stamp_ns), height=H, width=W, encoding=encoding, is_bigendian=0, step=step,
                          data=np.frombuffer(arr.tobytes(), dtype=np.uint8))

    def camera_info(self, stamp_ns, intr: CameraIntrinsics):
        k = np.array([intr.fx, 0, intr.cx, 0, intr.fy, intr.cy, 0, 0, 1], dtype=np.float64)
        r = np.eye(3).reshape(-1)
        p = np.array([intr.fx, 0, intr.cx, 0, 0, intr.fy, intr.cy, 0, 0, 0, 1, 0], dtype=np.float64)
        roi = self.ROI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self.CameraInfo(header=self.header(stamp_ns), height=intr.height, width=intr.width, distortion_model="plumb_bob",
                               d=np.zeros(5, dtype=np.float64), k=k, r=r, p=p, binning_x=0, binning_y=0, roi=roi)

    def points(self, stamp_ns, pts: np.ndarray):
        H, W = pts.shape[:2]
        F32 = 7  # sensor_msgs/PointField FLOAT32
        fields = [self.PointField(name=n, offset=4 * i, datatype=F32, count=1) for i, n in enumerate(("x", "y", "z", "rgb"))]
        data = np.frombuffer(np.ascontiguousarray(pts, dtype=np.float32).tobytes(), dtype=np.uint8)
        return self.PointCloud2(header=self.header(stamp_ns), height=H, width=W, fields=fields, is_bigendian=False,
                                point_step=16, row_step=16 * W, data=data, is_dense=False)

    def truth(self, stamp_ns, view: View, samples_per_pixel: float):
        values = {
            "label": str(view.label),
            "class_name": view.class_name,
            "scene_seed": str(view.scene_seed),
            "view_index": str(view.view_index),
            "width": str(view.intrinsics.width),
            "height": str(view.intrinsics.height),
            "samples_per_pixel": f"{samples_per_pixel:g}",
            "generator": "pws_ros.sim.dense_cloud_for(scene_seed, view_index, width, height, samples_per_pixel)",
            "classes": ",".join(CLASS_NAMES),
        }
        kvs = [self.KeyValue(key=k, value=v) for k, v in values.items()]
        status = self.DiagnosticStatus(level=0, name="ground_truth", message=view.class_name,
                                       hardware_id="pws_ros.sim", values=kvs)
        return self.DiagnosticArray(header=self.header(stamp_ns), status=[status])


def record(out: str | Path, frames: int = 36, *, storage: str = "mcap", seed: int = 0, width: int = 160, height: int = 90,
           views_per_scene: int = 3, period_s: float = 0.1, max_depth: float | None = None, compress: bool = True,
           samples_per_pixel: float = 6.0, points: bool = True, progress=None) -> Path:
    """Write ``frames`` views of the world as a rosbag2 bag at ``out`` (which must not exist);
    ``points=False`` leaves out the organized PointCloud2 (RGB-D, CameraInfo and ground truth only)."""
    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin

    out = Path(out)
    require(not out.exists(), f"output {out} already exists: choose a new directory")
    require(out.parent.is_dir() if str(out.parent) else True, f"parent directory of {out} does not exist")
    storage = str(storage).lower()
    require(storage in STORAGES, f"unknown storage {storage!r}: expected mcap or sqlite3")
    require(period_s > 0, f"period must be positive, got {period_s}")
    schedule = frame_schedule(frames, seed, views_per_scene)
    msgs = _Msgs()
    ts = msgs.ts
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    writer = Writer(out, version=9, storage_plugin=plugin)
    if compress and storage == "mcap":
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        topics = TOPICS if points else TOPICS_WITHOUT_POINTS
        conns = {topic: writer.add_connection(topic, msgtype, typestore=ts) for topic, msgtype in topics.items()}
        for i, (scene_seed, view_index) in enumerate(schedule):
            view = render_view(scene_seed, view_index, width, height, dense=False, max_depth=max_depth)
            stamp = START_NS + int(round(i * period_s * 1e9))
            items = [
                (TOPIC_INFO, msgs.camera_info(stamp, view.intrinsics)),
                (TOPIC_COLOR, msgs.image(stamp, view.rgb, "rgb8")),
                (TOPIC_DEPTH, msgs.image(stamp, depth_to_mm(view.depth), "16UC1")),
                (TOPIC_TRUTH, msgs.truth(stamp, view, samples_per_pixel)),
            ]
            if points:
                items.insert(3, (TOPIC_POINTS, msgs.points(stamp, organized_points(view))))
            for topic, msg in items:
                writer.write(conns[topic], stamp, ts.serialize_cdr(msg, TOPICS[topic]))
            if progress is not None:
                progress(i + 1, len(schedule), view)
    return out


# ------------------------------------------------------------------------------------------------
# reading back (verification; the ROS bridge has the general readers)
# ------------------------------------------------------------------------------------------------
@dataclass
class RecordedFrame:
    stamp_ns: int
    rgb: np.ndarray
    depth_m: np.ndarray
    points: np.ndarray | None      # (H, W, 3) float32, NaN where invalid; None: recorded without points
    point_rgb: np.ndarray | None   # (H, W, 3) uint8; None: recorded without points
    intrinsics: CameraIntrinsics
    truth: dict


def _stamp(msg) -> int:
    return int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)


def image_array(msg) -> np.ndarray:
    """An rgb8 / 16UC1 / mono16 sensor_msgs/Image as numpy (H, W, 3) uint8 or (H, W) uint16."""
    data = np.asarray(msg.data, dtype=np.uint8)
    if msg.encoding == "rgb8":
        return data.reshape(msg.height, msg.step)[:, : msg.width * 3].reshape(msg.height, msg.width, 3).copy()
    if msg.encoding in ("16UC1", "mono16"):
        dt = np.dtype(">u2" if msg.is_bigendian else "<u2")
        return data.reshape(msg.height, msg.step)[:, : msg.width * 2].copy().view(dt).reshape(msg.height, msg.width).astype(np.uint16)
    raise PwsError(f"unsupported image encoding {msg.encoding!r}")


def cloud_array(msg) -> tuple[np.ndarray, np.ndarray]:
    """Organized PointCloud2 with float32 x, y, z and packed rgb -> (H, W, 3) xyz, (H, W, 3) uint8."""
    offs = {f.name: int(f.offset) for f in msg.fields}
    require(all(k in offs for k in ("x", "y", "z", "rgb")), "point cloud lacks x, y, z or rgb fields")
    raw = np.asarray(msg.data, dtype=np.uint8).reshape(msg.height, msg.row_step)[:, : msg.width * msg.point_step]
    raw = np.ascontiguousarray(raw).reshape(msg.height, msg.width, msg.point_step)

    def f32(o):
        return np.ascontiguousarray(raw[..., o : o + 4]).view(np.float32)[..., 0]

    xyz = np.stack([f32(offs["x"]), f32(offs["y"]), f32(offs["z"])], axis=-1)
    return xyz, unpack_rgb(f32(offs["rgb"]))


def read_recording(path: str | Path) -> Iterator[RecordedFrame]:
    """Frames of a recording made by :func:`record` (grouped by header stamp), via rosbags AnyReader.
    A recording made with ``points=False`` gives frames whose ``points``/``point_rgb`` are None."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    require(path.exists(), f"recording not found: {path}")
    ts = get_typestore(Stores.ROS2_JAZZY)
    pending: dict[int, dict] = {}
    with AnyReader([path], default_typestore=ts) as reader:
        conns = [c for c in reader.connections if c.topic in TOPICS]
        present = {c.topic for c in conns}
        missing = sorted(set(TOPICS_WITHOUT_POINTS) - present)
        require(not missing, f"{path} is not a pws sim recording: it lacks {', '.join(missing)}")
        for conn, _t, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            st = _stamp(msg)
            pending.setdefault(st, {})[conn.topic] = msg
            if len(pending[st]) == len(present):
                yield _frame(st, pending.pop(st))


def _frame(stamp: int, m: dict) -> RecordedFrame:
    xyz, prgb = cloud_array(m[TOPIC_POINTS]) if TOPIC_POINTS in m else (None, None)
    status = m[TOPIC_TRUTH].status[0]
    truth = {kv.key: kv.value for kv in status.values}
    return RecordedFrame(stamp_ns=stamp, rgb=image_array(m[TOPIC_COLOR]), depth_m=image_array(m[TOPIC_DEPTH]).astype(np.float64) / 1000.0,
                         points=xyz, point_rgb=prgb, intrinsics=CameraIntrinsics.from_camera_info(m[TOPIC_INFO]), truth=truth)
