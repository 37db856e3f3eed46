"""One certified input frame -> the messages it publishes, in publication order (ROS-free).

The ``pipeline`` node, the ``certifier`` node and ``pws replay`` all build a frame's outputs with
:func:`frame_outputs`: the nodes only publish the list (:class:`OutputPublishers`), replay only writes
it to its bag. Topics are relative (``certification``, ...): the node's namespace, or replay's
``--namespace``, is put in front by the caller. The builders are those of
:mod:`pws_ros.bridge.msgbuild`, so the list holds rclpy or rosbags messages, whichever ``types``
namespace is passed.

Order (docs/ros2.md, "Outputs"): ``cloud``, ``cloud/camera_info``, ``plan/poses/<axis>`` (in plan
order, i.e. config axis order), ``rendered/preview`` (in the engine's order), ``certification/markers``,
``certified_label`` and ``certification`` **last**: when a frame's certification arrives, everything else it
publishes is out. (The overlay image, ``certification/overlay``, is drawn after the certification is out,
by the nodes' overlay thread: :class:`pws_ros.nodes._common.OverlayOutput`; not part of this list.)

What is in the list:

- an input that could not be converted (no ``frame``, no ``result``): the certification only (ERROR on
  every axis, the reason in each status' message);
- a converted ``frame``: ``cloud`` + ``cloud/camera_info`` when ``switches.cloud``;
- a ``result`` (:class:`~pws_ros.bridge.engine.FrameResult`): one ``plan/poses/<axis>`` per planned
  axis when ``switches.poses``, its previews when ``switches.preview``;
- a converted frame or a result: the markers when ``switches.markers``;
- a frame certified on every axis with one label (:func:`~pws_ros.bridge.diagnostics.certified_label`): its
  ``certified_label`` message when ``switches.certified_label``;
- always: the certification.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from ..core.result import STATUS_ERROR, Certificate
from . import msgbuild

CERTIFICATION = "certification"
MARKERS = "certification/markers"
CLOUD = "cloud"
CLOUD_INFO = "cloud/camera_info"
POSES = "plan/poses/{axis}"
PREVIEW = "rendered/preview"
CERTIFIED_LABEL = "certified_label"
OVERLAY = "certification/overlay"

# message class (attribute of a ``types`` namespace) of each output topic
TOPIC_TYPES: dict[str, str] = {
    CLOUD: "PointCloud2", CLOUD_INFO: "CameraInfo", POSES: "PoseArray", PREVIEW: "Image",
    MARKERS: "MarkerArray", CERTIFIED_LABEL: "DiagnosticArray", CERTIFICATION: "DiagnosticArray", OVERLAY: "Image",
}
_POSES_PREFIX = POSES.split("{")[0]


def topic_type(types: Any, rel: str) -> Any:
    """The message class of output topic ``rel`` (``plan/poses/<axis>`` for every axis)."""
    key = POSES if rel.startswith(_POSES_PREFIX) else rel
    return getattr(types, TOPIC_TYPES[key])


@dataclass(frozen=True)
class OutputSwitches:
    """Which optional outputs a caller publishes (the certification always goes out)."""

    cloud: bool = False
    markers: bool = True
    poses: bool = True
    preview: bool = False
    certified_label: bool = True

    @classmethod
    def from_config(cls, cfg: Any) -> "OutputSwitches":
        return cls(cloud=bool(cfg.publish_cloud), markers=bool(cfg.publish_markers), poses=bool(cfg.publish_poses),
                   preview=bool(cfg.publish_preview))


def frame_outputs(types: Any, header: Any, certificates: Sequence[Certificate], *, node_name: str, latency_ms: float,
                  compute_ms: Any, switches: OutputSwitches, frame: Any = None, result: Any = None) -> list[tuple[str, Any]]:
    """``[(relative topic, message), ...]`` of one input frame, in publication order (module docstring).

    ``header``: the source header of every message; ``certificates``: one per configured axis;
    ``latency_ms`` / ``compute_ms``: as :func:`~pws_ros.bridge.msgbuild.certificates_to_diagnostic_array`
    takes them; ``frame``: the converted input (``cloud``, ``intrinsics``) or None; ``result``: the
    engine's :class:`~pws_ros.bridge.engine.FrameResult` (``plans``, ``previews``) or None.
    """
    out: list[tuple[str, Any]] = []
    if frame is not None and switches.cloud:
        out.append((CLOUD, msgbuild.cloud_to_pointcloud2(header, frame.cloud, types)))
        out.append((CLOUD_INFO, msgbuild.camera_info_from_intrinsics(header, frame.intrinsics, types)))
    if result is not None:
        if switches.poses:
            for axis, plan in result.plans.items():
                out.append((POSES.format(axis=axis), msgbuild.plan_to_pose_array(header, plan, types)))
        if switches.preview:
            for _axis, _index, img in result.previews:
                out.append((PREVIEW, msgbuild.image_from_numpy(header, img, types)))
    if (frame is not None or result is not None) and switches.markers:
        out.append((MARKERS, msgbuild.markers_for(header, certificates, types)))
    label = msgbuild.certified_label_array(header, certificates, node_name=node_name, types=types) if switches.certified_label else None
    if label is not None:
        out.append((CERTIFIED_LABEL, label))
    out.append((CERTIFICATION, msgbuild.certificates_to_diagnostic_array(
        header, certificates, node_name=node_name, types=types, latency_ms=latency_ms, compute_ms=compute_ms)))
    return out


class CertifiedLabelWatch:
    """How long it has been since the last ``certified_label`` (a frame certified on every axis): the nodes'
    health status WARNs past ``certified_label_timeout_s``. The clock is the wall (monotonic) clock, as the
    health timer's, and starts with the first frame a node publishes: with no input at all nothing is
    said here (``frames_in`` says it). :meth:`saw` takes each frame's :func:`frame_outputs` list."""

    def __init__(self, clock: Callable[[], float] = time.monotonic):
        self.clock = clock
        self.count = 0                       # certified_label messages published
        self.since: float | None = None      # clock of the last one (of the first frame while there is none)

    def saw(self, outputs: Sequence[tuple[str, Any]]) -> None:
        if any(rel == CERTIFIED_LABEL for rel, _msg in outputs):
            self.count += 1
            self.since = self.clock()
        elif self.since is None:
            self.since = self.clock()

    def age_s(self) -> float:
        """Seconds since the last certified label (since the first frame when none yet); nan before any frame."""
        return float("nan") if self.since is None else self.clock() - self.since

    def warning(self, timeout_s: float) -> str:
        """The health WARN text past ``timeout_s`` (0: never), else ""."""
        age = self.age_s()
        if not timeout_s > 0 or not age > timeout_s:
            return ""
        when = f"for {age:.1f} s" if self.count else f"in the {age:.1f} s since the first frame"
        return f"no frame certified on every axis {when} (certified_label_timeout_s {timeout_s:g})"

    def counters(self) -> dict[str, Any]:
        """The health status' keys: ``certified_labels`` and ``since_certified_label_s``."""
        return {"certified_labels": self.count, "since_certified_label_s": round(self.age_s(), 3)}


def frame_error(certificates: Sequence[Certificate]) -> str:
    """The reason of a frame that failed on every axis ("" otherwise): the nodes' ``last_error``."""
    errors = [c for c in certificates if c.status == STATUS_ERROR]
    return errors[0].reason if errors and len(errors) == len(certificates) else ""


def summary_line(stamp_ns: int, certificates: Sequence[Certificate]) -> str:
    """The one log line a node writes per certified frame."""
    return f"frame {stamp_ns}: " + "; ".join(c.summary() for c in certificates)


class OutputPublishers:
    """Publishes :func:`frame_outputs` lists through a node context (``ctx.publisher(type, topic)``).

    Every publisher is created up front (``topics``, and ``plan/poses/<axis>`` for ``axes``; again on a
    parameter change with :meth:`update_axes`), in the node's callbacks, never from the worker thread,
    which may still run after shutdown began (creating a publisher then fails). A list naming a topic
    without a publisher skips it.
    """

    def __init__(self, ctx: Any, topics: Sequence[str] = (), axes: Sequence[str] = ()):
        self.ctx = ctx
        self.pubs: dict[str, Any] = {}
        for rel in topics:
            self._create(rel)
        self.update_axes(axes)

    def _create(self, rel: str) -> None:
        if rel not in self.pubs:
            self.pubs[rel] = self.ctx.publisher(topic_type(self.ctx.types, rel), rel)

    def update_axes(self, axes: Sequence[str]) -> None:
        for axis in axes:
            self._create(POSES.format(axis=axis))

    def publish(self, outputs: Sequence[tuple[str, Any]]) -> None:
        for rel, msg in outputs:
            pub = self.pubs.get(rel)
            if pub is not None:
                pub.publish(msg)


__all__ = ["CERTIFICATION", "CERTIFIED_LABEL", "CertifiedLabelWatch", "CLOUD", "CLOUD_INFO", "MARKERS", "OVERLAY", "OutputPublishers", "OutputSwitches",
           "POSES", "PREVIEW", "TOPIC_TYPES", "frame_error", "frame_outputs", "summary_line", "topic_type"]
