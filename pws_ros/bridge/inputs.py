"""The camera-input front end of ``cloud_listener`` and ``pipeline``, without ROS.

:class:`InputAssembler` receives the raw input messages (callbacks call ``on_points``, ``on_depth``,
``on_color``, ``on_info``, ``on_depth_info``) and returns a :class:`RawFrame` when one input frame is
complete: a PointCloud2 alone (intrinsics from the latest CameraInfo, the organized grid, or
``camera_info_file``), or a depth + colour pair matched by stamp within ``sync_tolerance_s`` (or, once
settled, within ``sync_max_skew_s``: unsynchronised drivers; :class:`.sync.StampMatcher`) (plus a
CameraInfo: the latest one, or stamp-matched with ``camera_info_sync: stamp``). Callbacks only
buffer; :func:`convert` (the slow part: message -> cloud) runs in the worker on the newest frame only.

Depth and colour that are not registered to each other are registered into the colour camera when
the depth -> colour extrinsic is known (:meth:`InputAssembler.set_extrinsic`: from TF or a driver's
extrinsics topic) and the depth stream's CameraInfo arrives; otherwise they are refused.

In ``input_mode: auto`` the first source that completes a frame is used from then on (the other is
ignored and counted), so a camera publishing both points and images is not certified twice; in the
nodes, once one of its frames converts (:meth:`InputAssembler.conversion_done`): a malformed message
cannot lock the other source out.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.cloud import Cloud
from ..core.errors import require
from ..core.registration import Extrinsic
from . import cloudconv, msgconv
from .config import PwsConfig, depth_info_topic, resolve_path
from .sync import StampMatcher


def _sync_ns(config: PwsConfig) -> dict[str, int]:
    """The stamp matcher's tolerances (ns) from the configuration (seconds)."""
    return {"tolerance_ns": int(round(config.sync_tolerance_s * 1e9)), "max_skew_ns": int(round(config.sync_max_skew_s * 1e9))}


@dataclass
class RawFrame:
    """The messages of one input frame (converted later by :func:`convert`)."""

    source: str                     # "pointcloud2" | "rgbd"
    stamp_ns: int
    header: Any
    messages: dict[str, Any] = field(default_factory=dict)  # points | depth, color | info, depth_info, extrinsic
    skew_ns: int = 0                # largest stamp difference between the matched messages (rgbd)


@dataclass
class InputFrame:
    """One converted input frame: the one-frame cloud in the source optical frame and its camera."""

    source: str
    stamp_ns: int
    header: Any
    cloud: Cloud
    intrinsics: CameraIntrinsics
    has_color: bool = True


class InputAssembler:
    """Buffers input messages and yields complete :class:`RawFrame` s (thread-safe)."""

    def __init__(self, config: PwsConfig):
        self.config = config
        self.mode = config.input_mode
        self._lock = threading.Lock()
        streams = ("depth", "color") + (("info",) if config.camera_info_sync == "stamp" else ())
        self.matcher = StampMatcher(streams, queue_size=config.sync_queue_size, **_sync_ns(config))
        self.latest_info: Any = None
        self.latest_depth_info: Any = None
        self.fallback: CameraIntrinsics | None = None
        if config.camera_info_file:
            self.fallback = CameraIntrinsics.from_yaml(resolve_path(config.camera_info_file, "camera info file"))
        self.ignored = 0        # messages of the source not in use (auto mode, or wrong mode)
        self.skipped = 0        # frames skipped by min_period_s
        self.frames = 0         # complete frames produced
        self._last_stamp: int | None = None
        self.locked_source: str | None = None if self.mode == "auto" else self.mode
        self._lock_confirmed = self.mode != "auto"   # auto: locked for good by the first frame that converts
        # a depth + colour pair matched before the CameraInfo it needs arrived (camera_info_sync: latest;
        # and the depth camera's, where depth must be registered): held (the newest one only) and
        # completed by that CameraInfo instead of being lost
        self._held: dict[str, Any] | None = None
        self._depth_info_topic = depth_info_topic(config)
        self.held_replaced = 0
        self.extrinsic: Extrinsic | None = None   # depth -> colour optical frame (registers unregistered depth)

    def reconfigure(self, config: PwsConfig) -> None:
        """New parameters at run time (``ros2 param set``): the config and the matcher's tolerances."""
        with self._lock:
            self.config = config
            for name, ns in _sync_ns(config).items():
                setattr(self.matcher, name, ns)

    # -- helpers --
    def _accept_source(self, source: str) -> bool:
        if self.locked_source is None:
            return True
        if self.locked_source != source:
            self.ignored += 1
            return False
        return True

    def _emit(self, frame: RawFrame) -> RawFrame | None:
        if self.locked_source is None:
            self.locked_source = frame.source   # tentative in auto mode until a frame converts (conversion_done)
        if self.config.min_period_s > 0 and self._last_stamp is not None and \
                0 <= frame.stamp_ns - self._last_stamp < self.config.min_period_s * 1e9:
            self.skipped += 1
            return None
        self._last_stamp = frame.stamp_ns
        self.frames += 1
        return frame

    def conversion_done(self, source: str, ok: bool) -> None:
        """The worker's verdict on a frame of ``source`` (the nodes call it after :func:`convert`). In
        ``auto`` mode the first source to complete a frame is used from then on only once one of its
        frames converts: a frame that fails before that (a malformed or hostile PointCloud2 on a
        camera's unused topic, say) releases the source, so it cannot shut the real camera out. Callers
        that never call this (``pws replay``) keep the first source, as before."""
        with self._lock:
            if self._lock_confirmed or self.locked_source != source:
                return
            if ok:
                self._lock_confirmed = True
            else:
                self.locked_source = None

    @property
    def dropped(self) -> int:
        """Input messages that could not be matched into a frame (stamp matching), plus depth +
        colour pairs replaced by a newer one while both waited for the first CameraInfo."""
        return self.matcher.total_dropped() + self.held_replaced

    @property
    def waiting_for_info(self) -> bool:
        """True while a depth + colour pair waits for a CameraInfo (see :meth:`_waits`)."""
        return self._held is not None

    def waiting_for(self) -> str:
        """What a held pair waits for, in words ("" when none is held)."""
        if self._held is None:
            return ""
        if self.latest_info is None and "info" not in self._held:
            return f"the colour CameraInfo ({self.config.camera_info_topic})"
        return f"the depth camera's CameraInfo ({self._depth_info_topic}), needed to register the depth"

    def set_extrinsic(self, extrinsic: Extrinsic | None) -> None:
        """The depth -> colour transform used to register depth that is not registered (None: refuse it)."""
        with self._lock:
            self.extrinsic = extrinsic

    # -- callbacks --
    def on_info(self, msg: Any) -> RawFrame | None:
        with self._lock:
            self.latest_info = msg
            if self.config.camera_info_sync == "stamp" and self._accept_source("rgbd"):
                return self._match("info", msg)
            return self._release_held()

    def on_depth_info(self, msg: Any) -> RawFrame | None:
        with self._lock:
            self.latest_depth_info = msg
            return self._release_held()

    def _waits(self, msgs: dict[str, Any]) -> bool:
        """Whether a matched pair still waits for a CameraInfo: the colour camera's (none yet), or the
        depth camera's where the depth is registered with an extrinsic and that topic is configured."""
        if "info" not in msgs and self.latest_info is None:
            return True
        return self.extrinsic is not None and bool(self._depth_info_topic) and self.latest_depth_info is None

    def _release_held(self) -> RawFrame | None:
        if self._held is None or self._waits(self._held):
            return None
        msgs, self._held = self._held, None
        return self._rgbd_frame(msgs)

    def on_points(self, msg: Any) -> RawFrame | None:
        with self._lock:
            if not self._accept_source("pointcloud2"):
                return None
            msgs = {"points": msg}
            if self.latest_info is not None:
                msgs["info"] = self.latest_info
            return self._emit(RawFrame("pointcloud2", msgconv.header_stamp_ns(msg), msg.header, msgs))

    def on_depth(self, msg: Any) -> RawFrame | None:
        with self._lock:
            if not self._accept_source("rgbd"):
                return None
            return self._match("depth", msg)

    def on_color(self, msg: Any) -> RawFrame | None:
        with self._lock:
            if not self._accept_source("rgbd"):
                return None
            return self._match("color", msg)

    def flush(self) -> RawFrame | None:
        """At the end of the input (a recording): the depth + colour pair that waited to be settled
        (``sync_max_skew_s``), if any."""
        with self._lock:
            if self.locked_source == "pointcloud2":
                return None
            return self._matched(self.matcher.flush())

    def _match(self, stream: str, msg: Any) -> RawFrame | None:
        return self._matched(self.matcher.add(stream, msgconv.header_stamp_ns(msg), msg))

    def _matched(self, got: Any) -> RawFrame | None:
        if got is None:
            return None
        msgs = dict(got.messages)
        msgs["skew_ns"] = max(got.stamps.values()) - min(got.stamps.values())
        if self._waits(msgs):
            # CameraInfo often starts a little after the images: hold the newest pair for it
            if self._held is not None:
                self.held_replaced += 1
            self._held = msgs
            return None
        return self._rgbd_frame(msgs)

    def _rgbd_frame(self, msgs: dict[str, Any]) -> RawFrame | None:
        """The frame of a matched pair; its CameraInfo is the stamp-matched one or the latest."""
        msgs.setdefault("info", self.latest_info)
        if self.latest_depth_info is not None:
            msgs["depth_info"] = self.latest_depth_info
        if self.extrinsic is not None:
            msgs["extrinsic"] = self.extrinsic
        skew = int(msgs.pop("skew_ns", 0))
        color = msgs["color"]
        return self._emit(RawFrame("rgbd", msgconv.header_stamp_ns(color), color.header, msgs, skew_ns=skew))

    def skew_warning(self, frame: RawFrame) -> str:
        """A WARN text for a pair matched beyond ``sync_tolerance_s`` (within ``sync_max_skew_s``), else ""."""
        if frame.skew_ns <= self.matcher.tolerance_ns:
            return ""
        return (f"depth and colour {frame.skew_ns / 1e6:.1f} ms apart (more than sync_tolerance_s = "
                f"{self.matcher.tolerance_ns / 1e9:g} s) paired as each other's nearest (sync_max_skew_s = "
                f"{self.matcher.max_skew_ns / 1e9:g} s): the cloud's geometry and colour are that far apart in time, "
                "so a moving camera certifies a misregistered cloud; sync_max_skew_s: 0 refuses such pairs")


def convert(frame: RawFrame, config: PwsConfig, fallback: CameraIntrinsics | None = None) -> InputFrame:
    """The one-frame cloud and camera of a :class:`RawFrame` (PwsError for bad input)."""
    m = frame.messages
    if frame.source == "pointcloud2":
        cloud, intr, has_color = cloudconv.cloud_and_intrinsics_from_pointcloud2(
            m["points"], m.get("info"), fallback, depth_fill=config.depth_fill, min_valid=config.min_valid_depth,
            max_depth=config.max_depth_m)
    else:
        require(frame.source == "rgbd", f"unknown input source {frame.source!r}")
        cloud, intr = msgconv.cloud_from_rgbd(m["depth"], m["color"], m["info"], m.get("depth_info"),
                                              require_same_frame=config.require_same_frame, extrinsic=m.get("extrinsic"),
                                              depth_fill=config.depth_fill, min_valid=config.min_valid_depth,
                                              max_depth=config.max_depth_m)
        has_color = True
        # the cloud as a PointCloud2 carries it (float32 x y z): the pipeline and the four-process chain
        # (where the cloud crosses a topic) then certify exactly the same points
        cloud = Cloud(cloud.points.astype(np.float32), cloud.colors, cloud.filled, cloud.filled_mask)
    require(len(cloud) > 0, f"the input frame has no valid point ({frame.source})")
    return InputFrame(frame.source, frame.stamp_ns, frame.header, cloud, intr, has_color)


__all__ = ["InputAssembler", "InputFrame", "RawFrame", "convert"]
