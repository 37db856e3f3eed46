"""Image files to a rosbag2 recording: what ``pws import frames`` and ``pws import tum`` write.

Per frame, all with the frame's header stamp (also the log time) and frame id
``camera_color_optical_frame``, on the topics ``pws replay`` reads by default (``config/pws.yaml``):

* ``/camera/color/camera_info``                sensor_msgs/CameraInfo (pinhole, no distortion)
* ``/camera/aligned_depth_to_color/image_raw`` sensor_msgs/Image 16UC1, millimetres, 0 = no depth
* ``/camera/color/image_raw``                  sensor_msgs/Image rgb8
* ``/pws/ground_truth``                        the frame's label (:mod:`pws_ros.replay.truth`), where it has one

The depth is taken as registered to the colour camera (the same pixels). Depth in metres is the
stored value times the depth scale (metres per unit); 0, negative, NaN or beyond 65.535 m is no depth.
The bag is written whole or not at all (:func:`pws_ros.bagio.whole_bag`).
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..bridge.config import PwsConfig
from ..core.camera import CameraIntrinsics
from ..core.errors import PwsError, require
from ..replay.options import GROUND_TRUTH_TOPIC

FRAME_ID = "camera_color_optical_frame"
COLOR_SUFFIXES = (".png", ".jpg", ".jpeg")
DEPTH_SUFFIXES = (".npy", ".png", ".tif", ".tiff")
_DEFAULTS = PwsConfig()
TOPICS = {"depth": _DEFAULTS.depth_topic, "color": _DEFAULTS.color_topic, "info": _DEFAULTS.camera_info_topic,
          "truth": GROUND_TRUTH_TOPIC}
HARDWARE_ID = "pws import"


@dataclass(frozen=True)
class Pinhole:
    """fx, fy, cx, cy (pixels, ROS/OpenCV pixel-centre convention) of the colour camera; ``width`` and
    ``height`` where the source states the image size (a camera_info YAML): every image must have it."""

    fx: float
    fy: float
    cx: float
    cy: float
    source: str = "--intrinsics"
    width: int | None = None
    height: int | None = None

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            require(math.isfinite(getattr(self, name)), f"{self.source}: {name} must be finite, got {getattr(self, name)}")
        require(self.fx > 0 and self.fy > 0, f"{self.source}: fx and fy must be positive, got {self.fx:g}, {self.fy:g}")

    @classmethod
    def parse(cls, text: str) -> "Pinhole":
        """``fx,fy,cx,cy`` (``--intrinsics``)."""
        try:
            values = [float(v) for v in str(text).split(",")]
        except ValueError:
            values = []
        require(len(values) == 4, f"--intrinsics: expected fx,fy,cx,cy (four numbers, pixels), got {text!r}")
        return cls(*values)

    @classmethod
    def from_yaml(cls, path: str | Path) -> "Pinhole":
        """A ROS camera_info YAML file (camera_calibration's format); it fixes the image size too."""
        c = CameraIntrinsics.from_yaml(path)
        return cls(c.fx, c.fy, c.cx, c.cy, f"camera file {path}", c.width, c.height)

    def camera(self, width: int, height: int, image: Path) -> CameraIntrinsics:
        if self.width is not None:
            require((width, height) == (self.width, self.height),
                    f"{image} is {width}x{height} but {self.source} is for {self.width}x{self.height} images")
        return CameraIntrinsics(int(width), int(height), self.fx, self.fy, self.cx, self.cy, FRAME_ID)

    def describe(self) -> str:
        return f"fx {self.fx:g}, fy {self.fy:g}, cx {self.cx:g}, cy {self.cy:g} ({self.source})"


@dataclass(frozen=True)
class ImportFrame:
    """One frame to write: its stamp, colour and depth files, the depth scale (metres per stored unit)
    and its ground-truth values (None: the frame has no label)."""

    stamp_ns: int
    color: Path
    depth: Path
    depth_scale: float
    truth: dict[str, str] | None = None


def check_depth_scale(scale: Any, source: str) -> float:
    try:
        value = float(scale)
    except (TypeError, ValueError):
        raise PwsError(f"{source}: the depth scale must be a number (metres per depth unit), got {scale!r}") from None
    require(math.isfinite(value) and value > 0,
            f"{source}: the depth scale must be positive (metres per depth unit, e.g. 0.001 for millimetres), got {scale!r}")
    return value


def read_color(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a colour image file."""
    import cv2

    require(Path(path).is_file(), f"colour image not found: {path}")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    require(bgr is not None and bgr.size > 0, f"{path}: not a readable image")
    return np.ascontiguousarray(bgr[..., ::-1])


def read_depth(path: Path) -> np.ndarray:
    """The stored depth values of a ``.npy`` array (2-D, numbers) or a 16-bit PNG / TIFF, as (H, W)."""
    import cv2

    path = Path(path)
    require(path.is_file(), f"depth file not found: {path}")
    if path.suffix.lower() == ".npy":
        try:
            raw = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise PwsError(f"{path}: not a readable .npy array ({' '.join(str(exc).split())[:160]})") from None
        require(raw.ndim == 2 and raw.size > 0 and (np.issubdtype(raw.dtype, np.integer) or np.issubdtype(raw.dtype, np.floating)),
                f"{path}: a depth array must be 2-D numbers (H, W), got {raw.dtype} of shape {raw.shape}")
        return raw
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    require(raw is not None and raw.size > 0, f"{path}: not a readable image")
    require(raw.ndim == 2 and raw.dtype in (np.uint16, np.float32),
            f"{path}: not a depth image (one channel, 16-bit or 32-bit float), got {raw.dtype} with "
            f"{1 if raw.ndim == 2 else raw.shape[2]} channel(s): an 8-bit picture of the depth cannot be used")
    return raw


def depth_to_mm(raw: np.ndarray, scale: float) -> np.ndarray:
    """Stored depth times ``scale`` (metres per unit) as 16UC1 millimetres; 0 where there is no depth
    (0, negative, not finite, beyond 65.535 m)."""
    with np.errstate(invalid="ignore", over="ignore"):
        mm = np.rint(np.asarray(raw, dtype=np.float64) * (float(scale) * 1000.0))
        ok = np.isfinite(mm) & (mm > 0) & (mm <= 65535)
    return np.where(ok, mm, 0).astype(np.uint16)


def write_frames(frames: Sequence[ImportFrame], out: Path, pinhole: Pinhole, *, overwrite: bool = False,
                 progress: Any = None) -> dict[str, Any]:
    """Write ``frames`` (stamps strictly increasing) as a rosbag2 MCAP recording at ``out``, whole or
    not at all; ``progress.update(1)`` after each frame. Returns what was written (frames, size, labels)."""
    from ..bagio import whole_bag
    from ..bridge import msgbuild
    from ..replay.interrupt import StopSignals
    from ..replay.truth import truth_message

    require(len(frames) > 0, "no frame to write")
    for a, b in zip(frames, frames[1:]):
        require(b.stamp_ns > a.stamp_ns, f"{b.color}: its stamp {b.stamp_ns} ns does not come after {a.color}'s ({a.stamp_ns} ns)")
    types = msgbuild.rosbags_types()
    sizes: Counter = Counter()
    labels: Counter = Counter()
    with StopSignals(), whole_bag(out, overwrite=overwrite, typestore=types.typestore) as writer:
        for f in frames:
            rgb = read_color(f.color)
            raw = read_depth(f.depth)
            require(raw.shape == rgb.shape[:2], f"{f.depth} ({raw.shape[1]}x{raw.shape[0]}) and {f.color} "
                                                f"({rgb.shape[1]}x{rgb.shape[0]}) differ in size: the depth must be registered to the colour image")
            h, w = raw.shape
            cam = pinhole.camera(w, h, f.color)
            header = msgbuild.make_header(types, f.stamp_ns, FRAME_ID)
            writer.write(TOPICS["info"], msgbuild.camera_info_from_intrinsics(header, cam, types), f.stamp_ns)
            writer.write(TOPICS["depth"], msgbuild.image_from_numpy(header, depth_to_mm(raw, f.depth_scale), types, "16UC1"), f.stamp_ns)
            writer.write(TOPICS["color"], msgbuild.image_from_numpy(header, rgb, types, "rgb8"), f.stamp_ns)
            if f.truth is not None:
                writer.write(TOPICS["truth"], truth_message(types, header, f.truth, hardware_id=HARDWARE_ID), f.stamp_ns)
                labels[f.truth.get("class_name", "")] += 1
            sizes[f"{w}x{h}"] += 1
            if progress is not None:
                progress.update(1)
    size = sum(p.stat().st_size for p in Path(out).iterdir() if p.is_file())
    return {"out": str(out), "frames": len(frames), "sizes": dict(sizes), "labels": dict(sorted(labels.items())),
            "bytes": int(size), "intrinsics": pinhole.describe(), "topics": [t for k, t in TOPICS.items() if k != "truth" or labels]}
