"""``cloud_listener``: builds the one-frame coloured cloud in the camera optical frame.

Inputs (sensor-data QoS by default): an organized or unorganized ``PointCloud2`` on ``points_topic``,
or a registered depth ``Image`` (16UC1 mm / 32FC1 m) on ``depth_topic`` + colour ``Image`` on
``color_topic`` + ``CameraInfo`` on ``camera_info_topic``, matched by stamp. Outputs (reliable):
``cloud`` (PointCloud2 x, y, z, rgb, and ``pws_filled`` where depth was filled; source header) and ``cloud/camera_info`` (the intrinsics, same
header). Health on ``/diagnostics``. Bad input is logged (throttled) and counted, never fatal; an input
frame that cannot be converted is reported on ``cloud/errors`` (``std_msgs/String``, see
:mod:`pws_ros.bridge.scheme`), which the planner and the certifier turn into that frame's ERROR
certification, as the pipeline node publishes it for bad input.
"""
from __future__ import annotations

from typing import Any

from ..bridge import msgbuild, scheme
from ..bridge.inputs import RawFrame, convert
from ..core.errors import PwsError
from ._common import HealthPublisher, InputFrontend, Worker, entry_point, WorkerNode

NODE_NAME = "cloud_listener"


class CloudListenerNode(WorkerNode):
    def __init__(self, ctx: Any):

        self.ctx = ctx
        ctx.on_change = self._on_change
        T = ctx.types
        self.pub_cloud = ctx.publisher(T.PointCloud2, "cloud")
        self.pub_info = ctx.publisher(T.CameraInfo, "cloud/camera_info")
        self.pub_errors = ctx.publisher(T.String, "cloud/errors")
        self.published = 0
        self.failed = 0
        self.worker = Worker("pws-listener", self._process, ctx.log)
        self.frontend = InputFrontend(ctx, self.worker.submit)
        self.health = HealthPublisher(ctx, self._counters)

    def _on_change(self, cfg: Any) -> None:
        self.frontend.assembler.reconfigure(cfg)

    def _process(self, raw: RawFrame) -> None:
        T = self.ctx.types
        try:
            frame = convert(raw, self.ctx.config, self.frontend.assembler.fallback)
        except Exception as exc:  # noqa: BLE001 - bad input: the frame's ERROR certification comes from the certifier
            self.frontend.assembler.conversion_done(raw.source, False)
            reason = str(exc) if isinstance(exc, PwsError) else f"unexpected {type(exc).__name__}: {exc}"
            self.pub_errors.publish(scheme.input_error_message(raw.stamp_ns, str(raw.header.frame_id), reason, T))
            self.failed += 1
            raise PwsError(f"input: {reason}") from None
        self.frontend.assembler.conversion_done(raw.source, True)
        # camera_info first: the planner pairs the two by stamp
        self.pub_info.publish(msgbuild.camera_info_from_intrinsics(raw.header, frame.intrinsics, T))
        self.pub_cloud.publish(msgbuild.cloud_to_pointcloud2(raw.header, frame.cloud, T))
        self.published += 1
        if not frame.has_color and self.published == 1:
            self.ctx.log("warn", "the PointCloud2 has no rgb/rgba field: points are grey (0.5)")

    def _counters(self) -> dict[str, Any]:
        w = self.worker
        return {"activity": "converted", "rate_hz": w.rate.rate(), "frames_in": self.frontend.assembler.frames, "frames_processed": self.published,
                "frames_dropped": w.slot.dropped + self.frontend.dropped, "device": "cpu", "last_error": "",
                "warning": w.last_error, "extra": {"input_messages": self.frontend.received, "time_jumps_back": self.frontend.time_jumps,
                                                "failed_inputs": self.failed}}


main = entry_point(NODE_NAME, CloudListenerNode)


if __name__ == "__main__":
    main()
