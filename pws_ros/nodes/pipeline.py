"""``pipeline``: the four nodes in one process (listener -> planner -> projector -> certifier).

Frames and bounds are handed over in memory (no serialisation of thousands of frames). Callbacks only
buffer the inputs; a worker thread certifies the newest complete input frame (older ones are dropped
and counted: certification is slower than the camera), so callbacks and parameter services stay
responsive.

Several pipelines may share one input stream (``num_workers`` / ``worker_index``; ``ros2 launch pws_ros
pws.launch.py workers:=N``): each certifies only the frames whose stamp is assigned to it
(:class:`~pws_ros.bridge.workers.StampAssignment`, no coordinator), keeps its own latest-only mailbox,
and uses cores / num_workers torch threads; all publish on the same ``certification`` topic.

Subscribes (sensor-data QoS by default): ``points_topic`` (PointCloud2) or ``depth_topic`` +
``color_topic`` (Image) + ``camera_info_topic`` (CameraInfo) [+ ``depth_camera_info_topic``].
Publishes (reliable): ``certification`` (DiagnosticArray, one per processed input frame, header =
source header, one status ``pws/<axis>`` per axis; key schema in :mod:`pws_ros.bridge.msgbuild`),
``certified_label`` (DiagnosticArray, only for a frame certified on every axis), ``certification/markers``
(MarkerArray), ``cloud`` (PointCloud2) + ``cloud/camera_info``, ``plan/poses/<axis>`` (PoseArray),
``rendered/preview`` (Image rgb8), ``certification/overlay`` (Image rgb8, ``publish_overlay``) and
``/diagnostics`` (health).
"""
from __future__ import annotations

from typing import Any

from ..bridge import outputs
from ..bridge.inputs import RawFrame, convert
from ..bridge.preview import alpha0_view
from ..bridge.workers import StampAssignment, set_torch_threads
from ..core.errors import PwsError
from ._common import HealthPublisher, InputFrontend, OverlayOutput, Worker, entry_point, WorkerNode

NODE_NAME = "pipeline"


class PipelineNode(WorkerNode):
    """The logic of the pipeline node, composed around an rclpy ``Node``."""

    def __init__(self, ctx: Any):
        from ..bridge.engine import FrameCertifier

        self.ctx = ctx
        ctx.on_change = self._on_change
        self.assignment = StampAssignment.from_config(ctx.config)   # read-only: fixed for the node's life
        self.other_workers = 0            # frames assigned to another worker (not ours to certify)
        set_torch_threads(ctx.config.num_workers, ctx.log)
        self.engine = FrameCertifier(ctx.config, log=ctx.log)  # loads the model now (PwsError -> exit 2)
        self.pubs = outputs.OutputPublishers(ctx, (outputs.CERTIFICATION, outputs.CERTIFIED_LABEL, outputs.MARKERS, outputs.CLOUD,
                                                   outputs.CLOUD_INFO, outputs.PREVIEW), axes=ctx.config.axes)
        self.overlay = OverlayOutput(ctx)
        self.frame_errors = 0
        self.last_frame_error = ""
        self.worker = Worker("pws-pipeline", self._process, ctx.log)
        self.frontend = InputFrontend(ctx, self._on_frame)
        self.health = HealthPublisher(ctx, self._counters, certifying=True, overlay=self.overlay)
        coverage = f"coverage {ctx.config.coverage}, " if ctx.config.method != "cms" else ""  # cms has no coverage rule
        ctx.log("info", f"pipeline ready: axes {', '.join(ctx.config.axes)}, method {ctx.config.method}, "
                        f"{coverage}device {self.engine.device}")
        if self.assignment.num_workers > 1:
            ctx.log("info", self.assignment.describe())

    def _on_change(self, cfg: Any) -> None:
        self.frontend.assembler.reconfigure(cfg)
        self.pubs.update_axes(cfg.axes)
        self.overlay.update(cfg)

    def _on_frame(self, raw: RawFrame) -> None:
        if not self.assignment.mine(raw.stamp_ns):
            self.other_workers += 1
            return
        self.worker.submit(raw)

    def _process(self, raw: RawFrame) -> None:
        ctx = self.ctx
        cfg = ctx.config
        self.engine.config = cfg  # parameter changes apply between frames
        try:
            frame = convert(raw, cfg, self.frontend.assembler.fallback)
        except Exception as exc:  # noqa: BLE001 - bad input: this frame's certification is an ERROR
            self.frontend.assembler.conversion_done(raw.source, False)
            reason = str(exc) if isinstance(exc, PwsError) else f"unexpected {type(exc).__name__}: {exc}"
            self.frame_errors += 1
            self.last_frame_error = f"input: {reason}"
            certs = [self.engine.error_for(a, f"input: {reason}") for a in cfg.axes]
            self._publish(raw, certs, compute_ms=0.0)
            raise PwsError(f"input: {reason}") from None
        self.frontend.assembler.conversion_done(raw.source, True)
        result = self.engine.process(frame.cloud, frame.intrinsics, raw.stamp_ns, frame_id=raw.header.frame_id,
                                     preview_every=cfg.preview_every if cfg.publish_preview else 0,
                                     should_stop=lambda: self.worker.stopping)
        self._publish(raw, result.certificates, compute_ms=result.compute_ms, frame=frame, result=result,
                      view=lambda: alpha0_view(result, self.engine.source_cloud(frame.cloud), device=self.engine.device))
        self.last_frame_error = outputs.frame_error(result.certificates)
        ctx.log("info", outputs.summary_line(raw.stamp_ns, result.certificates))

    def _publish(self, raw: RawFrame, certs: list[Any], *, compute_ms: Any, frame: Any = None, result: Any = None,
                 view: Any = None) -> None:
        """Publish one frame's outputs (:func:`~pws_ros.bridge.outputs.frame_outputs`: the certification last),
        then hand it to the overlay (``view()``: its α = 0 frame, made in the overlay's thread)."""
        ctx = self.ctx
        out = outputs.frame_outputs(
            ctx.types, raw.header, certs, node_name=ctx.name, latency_ms=(ctx.now_ns() - raw.stamp_ns) / 1e6,
            compute_ms=compute_ms, switches=outputs.OutputSwitches.from_config(self.engine.config),  # this frame's config
            frame=frame, result=result)
        self.pubs.publish(out)
        self.health.published(out)
        self.overlay.submit(raw.header, raw.stamp_ns, certs, view or (lambda: None))

    def _counters(self) -> dict[str, Any]:
        w = self.worker
        return {
            "activity": "certified",
            "rate_hz": w.rate.rate(),
            "frames_in": self.frontend.assembler.frames,
            "frames_processed": w.processed,
            "frames_dropped": w.slot.dropped + self.frontend.dropped,
            "device": self.engine.device,
            "last_error": self.last_frame_error,
            "warning": self.engine.device_warning,
            "extra": {"busy": w.busy, "input_messages": self.frontend.received, "unmatched_inputs": self.frontend.dropped,
                      "ignored_inputs": self.frontend.assembler.ignored, "skipped_by_min_period": self.frontend.assembler.skipped,
                      "time_jumps_back": self.frontend.time_jumps, "other_workers_frames": self.other_workers},
        }


main = entry_point(NODE_NAME, PipelineNode)


if __name__ == "__main__":
    main()
