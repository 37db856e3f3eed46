"""``projector``: renders one frame per planned pose and the per-segment bounds the core reports.

Subscribes (reliable): ``plan/cloud`` (PointCloud2: the cloud of each planned frame, handed on by
``partition_planner``; the last few are kept by stamp) and ``plan`` (plan bundles). For the newest plan bundle (older ones not yet
started are dropped and counted) it renders every axis and publishes, in this order per axis,
``rendered/frames`` (Image 32FC3, ``header.frame_id = "<stamp_ns>/<axis>/<index>/<count>"``, reliable,
history ``frames_qos_depth``) and ``rendered/bounds`` (Float64MultiArray), or ``rendered/errors`` when
the axis cannot be rendered; plus a decimated ``rendered/preview`` (Image rgb8, source header).
Wire scheme: :mod:`pws_ros.bridge.scheme`.

Every axis of a plan it takes ends in its frames and bounds or in a ``rendered/errors`` message (a
malformed ``plan/cloud``, a cloud that never came, a failed rendering), so the certifier answers every
such frame. A malformed message is a throttled WARN naming the topic; no callback raises.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any

from ..bridge import cloudconv, msgbuild, msgconv, scheme
from ..bridge.preview import preview_frames
from ..core.errors import PwsError, require
from ._common import HealthPublisher, Throttle, Worker, guarded, stage_engine, entry_point, WorkerNode

NODE_NAME = "projector"
CLOUD_WAIT_S = 2.0


class ProjectorNode(WorkerNode):
    def __init__(self, ctx: Any):
        self.ctx = ctx
        T = ctx.types
        cfg = ctx.config
        self.engine = stage_engine(ctx)
        self.clouds: OrderedDict[int, Any] = OrderedDict()
        self.max_clouds = 2 * cfg.max_pending_frames + 2
        self._cloud_cond = threading.Condition()
        self.rendered_sets = 0
        self.frames_published = 0
        self.pub_frames = ctx.publisher(T.Image, "rendered/frames", kind="reliable", depth=cfg.frames_qos_depth)
        self.pub_bounds = ctx.publisher(T.Float64MultiArray, "rendered/bounds", kind="reliable", depth=max(10, cfg.output_qos_depth))
        self.pub_errors = ctx.publisher(T.String, "rendered/errors", kind="reliable", depth=max(10, cfg.output_qos_depth))
        self.pub_preview = ctx.publisher(T.Image, "rendered/preview")
        self.throttle = Throttle()
        self.worker = Worker("pws-projector", self._process, ctx.log)
        self.subs = [
            ctx.subscription(T.PointCloud2, "plan/cloud", guarded(ctx, self.throttle, "plan/cloud", self._on_cloud),
                             kind=cfg.output_qos, depth=cfg.output_qos_depth),
            ctx.subscription(T.String, "plan", guarded(ctx, self.throttle, "plan", self._on_plan), kind=cfg.output_qos,
                             depth=cfg.output_qos_depth),
        ]
        self.health = HealthPublisher(ctx, self._counters)

    def _on_cloud(self, msg: Any) -> None:
        stamp = scheme.check_stamp(msgconv.header_stamp_ns(msg), "plan/cloud")
        with self._cloud_cond:
            self.clouds.pop(stamp, None)  # a looped bag repeats stamps: the newest arrival is the newest entry
            self.clouds[stamp] = msg
            while len(self.clouds) > self.max_clouds:
                self.clouds.popitem(last=False)
            self._cloud_cond.notify_all()

    def _on_plan(self, msg: Any) -> None:
        bundle = scheme.parse_plan_bundle_message(msg, self.ctx.config.max_partitions)
        if bundle.plans:
            self.worker.submit(bundle)

    def _cloud_for(self, stamp_ns: int) -> Any:
        with self._cloud_cond:
            self._cloud_cond.wait_for(lambda: stamp_ns in self.clouds or self.worker.stopping, timeout=CLOUD_WAIT_S)
            return self.clouds.get(stamp_ns)

    def _process(self, bundle: scheme.PlanBundle) -> None:
        T = self.ctx.types
        self.engine.config = cfg = self.ctx.config
        S = bundle.stamp_ns
        cloud_msg = self._cloud_for(S)
        if cloud_msg is None:
            for axis in bundle.plans:
                self.pub_errors.publish(scheme.render_error_message(S, axis, f"no cloud with stamp {S} arrived within {CLOUD_WAIT_S:g} s", T))
            return
        try:
            cloud, _ = cloudconv.cloud_from_pointcloud2(cloud_msg)
            require(len(cloud) > 0, "the cloud has no valid point")
        except Exception as exc:  # noqa: BLE001 - a malformed plan/cloud: every axis of the frame is an ERROR
            reason = f"malformed plan/cloud: {exc}" if isinstance(exc, PwsError) else f"plan/cloud: unexpected {type(exc).__name__}: {exc}"
            for axis in bundle.plans:
                self.pub_errors.publish(scheme.render_error_message(S, axis, reason, T))
            raise PwsError(f"frame {S}: {reason}") from None
        for axis, plan in bundle.plans.items():
            if self.worker.stopping:
                return
            try:
                rendered = self.engine.render_axis(cloud, bundle.imaging or bundle.camera, plan)
            except PwsError as exc:
                self.pub_errors.publish(scheme.render_error_message(S, axis, str(exc), T))
                continue
            except Exception as exc:  # noqa: BLE001 - the certifier must hear of this axis
                self.pub_errors.publish(scheme.render_error_message(S, axis, f"internal error ({type(exc).__name__}): {exc}", T))
                self.ctx.log("error", f"frame {S} axis {axis}: rendering failed: {type(exc).__name__}: {exc}")
                continue
            n = len(plan.alphas)
            for i in range(n):
                self.pub_frames.publish(scheme.frame_message(S, axis, i, n, rendered.frames[i], T))
            self.frames_published += n
            self.pub_bounds.publish(scheme.bounds_message(S, axis, rendered, T))
            if cfg.publish_preview:
                for _a, _i, img in preview_frames(axis, rendered, cfg.preview_every):
                    self.pub_preview.publish(msgbuild.image_from_numpy(cloud_msg.header, img, T))
        self.rendered_sets += 1

    def _counters(self) -> dict[str, Any]:
        w = self.worker
        return {"activity": "rendered", "rate_hz": w.rate.rate(), "frames_in": w.slot.accepted, "frames_processed": self.rendered_sets,
                "frames_dropped": w.slot.dropped, "device": self.engine.device, "last_error": "", "warning": w.last_error,
                "extra": {"frames_published": self.frames_published}}

    def close(self) -> None:
        super().close()
        with self._cloud_cond:
            self._cloud_cond.notify_all()


main = entry_point(NODE_NAME, ProjectorNode)


if __name__ == "__main__":
    main()
